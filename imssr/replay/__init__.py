"""Replay storage: the numpy host store and the tensor store on a device (``train.replay_device``)."""
from imssr.replay.buffer import FrameReplayBuffer, ReplayMemoryWarning, available_memory_bytes
from imssr.replay.device import (ReplayPlacement, TensorFrameReplayBuffer, choose_replay_device, make_replay_buffer,
                                 replay_placement)

__all__ = ["FrameReplayBuffer", "ReplayMemoryWarning", "ReplayPlacement", "TensorFrameReplayBuffer",
           "available_memory_bytes", "choose_replay_device", "make_replay_buffer", "replay_placement"]
