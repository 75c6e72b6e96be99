"""Neural networks: pixel encoder, actor, critic."""
from imssr.networks.encoder import ConvTrunk, Encoder, Projection, conv_output_size, shapes_only, weight_init
from imssr.networks.heads import Actor, Critic, PolicyOutput, QHeads, mlp
from imssr.networks.module import ema

__all__ = ["ConvTrunk", "Encoder", "Projection", "conv_output_size", "shapes_only", "weight_init",
           "Actor", "Critic", "PolicyOutput", "QHeads", "mlp", "ema"]
