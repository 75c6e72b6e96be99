"""PAD's plug-in declaration: its preset rows and those of IM-PAD (no torch here; the task is
:mod:`imssr.auxiliary.pad`)."""
from imssr.settings import DMCGB, TABLE3, AuxPlugin, Beta0, Setting

PLUGIN = AuxPlugin(
    name="pad", label="PAD", implementation="PAD",
    description="SAC + PAD's inverse-dynamics task, shared 8 of 11 conv layers (Hansen et al. 2021)",
    preset=(
        Setting("agent.encoder_layers", 11, TABLE3),
        Setting("agent.encoder_head_layers", 3, DMCGB, "8 shared + 3 head layers"),
        Setting("aux.lr", 1e-3, DMCGB, "aux_lr"),
        Setting("aux.update_every", 1, TABLE3, "deviation from DMC-GB and the authors' code (every "
                "2nd agent step, their parser default; their pad.sh sets nothing): Table III wins"),
        Setting("aux.own_batch", True, TABLE3, "deviation from DMC-GB (PAD on the RL batch of "
                "128): Table III gives PAD an SSL batch of 256"),
        Setting("aux.batch_size", 256, TABLE3),
        Setting("train.replay_capacity", 500_000, TABLE3),
    ),
    # The paper reports beta_0 = 0.05 for IM-PAD (on pendulum_swingup) and no other value; the
    # authors' code has no IM-PAD, so its normalisation follows IM-CURL's (the default).
    beta0=Beta0(every_task=0.05, every_task_source="paper (beta_0 = 0.05 for IM-PAD / IM-SVEA)"),
)
