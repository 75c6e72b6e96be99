"""The sections of a run's config that no plug-in owns, and the cores of those it composes.

One typed dataclass per section, one docstring per field.  Counters count agent steps and replay
capacity counts transitions (:mod:`imssr.config` says the units).  The ``aux`` and ``intrinsic``
sections are a core here (:class:`AuxCore`, :class:`IntrinsicCore`) plus the settings of every
auxiliary task and intrinsic signal, which each plug-in declares beside its code;
:mod:`imssr.config.schema` composes them.  Besides the sections: the allowed values the rules of
:mod:`imssr.config.validation` check.
"""
from __future__ import annotations

from dataclasses import dataclass


@dataclass
class EnvConfig:
    task: str = "cartpole_swingup_sparse"
    """Task name, paper-style ``domain_task`` (``imssr tasks`` lists them)."""
    mode: str = "training"
    """Scene the agent trains in (``imssr modes``: training, color_*, video_*, distracting_*)."""
    footage_dir: str = ""
    """Videos or frame folders (mp4 files, DAVIS ``JPEGImages/480p``) for video backgrounds;
    empty: ``$IMSSR_FOOTAGE_DIR`` if set, else built-in footage.  Training envs draw from the
    ``train`` half of the clips, evaluation envs from the unseen ``test`` half."""
    action_repeat: int = 8
    """Environment frames per agent step (Table III: 2 finger_spin, 8 cartpole/pendulum, else 4)."""
    image_size: int = 100
    """Rendered frame height and width in pixels."""
    frame_stack: int = 3
    """Frames stacked (channels first) into one observation."""
    shadow_size: int = 512
    """MuJoCo shadow-map size in pixels (the suite's default is 2048; 512 steps the env 1.7-2.2x
    faster and changes pixels by 0.003-0.025 grey levels on average; docs/performance.md); at
    most 4096, MuJoCo's default: a larger map sharpens no shadow of a frame of at most 480 px."""


@dataclass
class AgentConfig:
    encoder_layers: int = 4
    """Convolutional layers of the shared pixel encoder (Table III: 4 CURL, 11 SODA/PAD/SVEA)."""
    encoder_head_layers: int = 0
    """Of ``encoder_layers``, how many (the last) form the RL head; an auxiliary task with a
    head of its own (PAD: 3 of 11) shares only the first ``encoder_layers - encoder_head_layers``."""
    encoder_filters: int = 32
    """Filters per convolutional layer."""
    channels_last: bool = True
    """Run the encoder's convolutions on NHWC activations (faster on CPU and GPU; same maths,
    float rounding may differ in the last bits)."""
    final_relu: bool = False
    """ReLU after the last convolution (official CURL: true; DMC-GB, whose encoder the authors
    ran for every algorithm: false, a ReLU only between convolutions)."""
    feature_dim: int = 100
    """Size of the encoder's projection (Linear + LayerNorm) output (DMC-GB 100, official CURL 50)."""
    projection_tanh: bool = True
    """Apply tanh after the LayerNorm of the critic's and actor's projections (DMC-GB: true;
    official CURL: false)."""
    hidden_dim: int = 1024
    """Width of the two hidden layers of the actor and of each Q head."""
    crop_size: int = 84
    """Random crop (training) / centre crop (acting) size from ``image_size``; at least 3, and
    enough for ``encoder_layers`` to leave a pixel."""
    discount: float = 0.99
    """Discount factor gamma."""
    batch_size: int = 128
    """RL batch size N."""
    critic_lr: float = 1e-3
    """Adam learning rate of the critic (including the encoder)."""
    critic_beta1: float = 0.9
    """Adam beta1 of the critic, in [0, 1)."""
    actor_lr: float = 1e-3
    """Adam learning rate of the actor (its head; the convs belong to the critic)."""
    actor_beta1: float = 0.9
    """Adam beta1 of the actor, in [0, 1)."""
    alpha_lr: float = 1e-4
    """Adam learning rate of the log temperature."""
    alpha_beta1: float = 0.5
    """Adam beta1 of the log temperature, in [0, 1)."""
    init_temperature: float = 0.1
    """Initial SAC temperature alpha."""
    critic_tau: float = 0.01
    """EMA rate of the target Q heads."""
    encoder_tau: float = 0.05
    """EMA rate of the target encoder (also CURL's key encoder)."""
    actor_update_every: int = 2
    """Agent steps between actor and temperature updates."""
    critic_update_every: int = 1
    """Agent steps between critic updates."""
    target_update_every: int = 2
    """Agent steps between target-network soft updates."""
    log_std_min: float = -10.0
    """Lower bound of the actor's log standard deviation."""
    log_std_max: float = 2.0
    """Upper bound of the actor's log standard deviation."""
    update_schedule: str = "sequential"
    """``sequential``: critic step, actor step on a fresh encoding of ``o``, target EMA, then the
    auxiliary step, as the CURL / DMC-GB code bases do (the paper's setting).  ``fused``: one
    online encoder pass over ``o`` feeds the critic, the actor (detached, DrQ-v2 style) and, for
    tasks that can reuse it (CURL, PAD), the auxiliary loss, whose gradient joins the critic's in one
    backward pass; fewer encoder passes (docs/performance.md), not update-for-update equal to
    the reference.  Needs ``critic_update_every = 1``."""
    precision: str = "fp32"
    """``fp32``: every pass in float32 (the paper's setting).  ``bf16``: mixed precision, the
    forward passes of the update, acting and evaluation under bfloat16 autocast (CPU or CUDA)
    while weights, gradients and Adam's state stay float32; the Bellman target, the InfoNCE
    logits, the per-sample losses behind r_int and their normalisation, LayerNorm, BatchNorm
    and the temperature stay float32 (docs/performance.md, "Mixed precision")."""
    q_heads_fp32: bool = False
    """Under ``precision = bf16``, run the twin Q heads (the MLPs on ``[z, a]``, online and target)
    in float32; the encoder stays bfloat16.  One state's Q varies over actions by only a few
    percent of Q's size, about bfloat16's resolution (``scripts/bf16_fidelity.py --split``).  No
    effect at ``fp32``."""
    tf32: str = "default"
    """TensorFloat-32 on CUDA (about 10 mantissa bits instead of 23; faster on Ampere and later):
    ``default``: PyTorch's own defaults, TF32 in cuDNN convolutions and full float32 matmuls (the
    authors' GPU runs); ``true``: TF32 in matmuls and convolutions; ``false``: strict float32 in
    both.  No effect on CPU."""
    compile: str = "off"
    """``torch.compile`` the conv trunks' passes, projections, Q heads and the actor's layers
    with inductor in this mode: ``off``, ``default`` or ``max-autotune`` (inductor's
    ``max-autotune-no-cudagraphs``).  It makes kernels only; CUDA graphs are :attr:`cuda_graphs`,
    which records the compiled kernels too.  The first updates are slow while it compiles; needs
    a C++ compiler on CPU."""
    fused_adam: bool = False
    """Step the SAC and auxiliary optimisers with torch's fused Adam (one kernel per parameter
    group on CUDA, instead of the foreach kernels torch uses by default).  The same update rule;
    the float rounding differs in the last bits (about 1e-7 relative), so it is off in the paper
    presets.  An intrinsic signal's own optimiser (RND's predictor) keeps torch's default."""
    cuda_graphs: bool = False
    """On CUDA, record each kind of update (forward, backward and every optimiser step) and the
    action pass once as a CUDA graph and replay it at every agent step: one launch instead of
    hundreds of kernels issued from Python (``imssr.agents.graphs``).  The same update rule;
    Adam then computes its bias correction on the device (``capturable``), which rounds the
    last bits differently, so it is off in the paper presets.  With :attr:`compile`, the compiled
    kernels are recorded.  On CPU the steps run eagerly, with the same numbers as without it."""
    batch_layout: str = "auto"
    """How the seeds of one process (``imssr train --seeds`` / ``--runs``, a sweep's packed runs)
    share the device: ``auto`` and ``streams`` alike, each member an agent of its own
    (``imssr.agents.members``) whose work on CUDA goes to a stream of its own, so that the
    members' kernels may run side by side (not measured on a GPU); on the CPU one after another,
    bit for bit each run alone.  A saved config's ``vmap`` or ``loop`` (stacked weights, refused
    for a new run) resumes as the same batch.  A run alone trains the same whatever it says."""

    @property
    def precision_label(self) -> str:
        """The run's numerics as reports and exports group them: ``precision``, and
        ``bf16-fp32q`` for bf16 with :attr:`q_heads_fp32` (other numbers, so never a seed of
        ``bf16``'s row)."""
        return "bf16-fp32q" if self.precision == "bf16" and self.q_heads_fp32 else self.precision


@dataclass
class AuxCore:
    """The settings of the ``aux`` section every auxiliary task reads; each task adds its own
    (its ``*_spec.py``), and :class:`imssr.config.AuxConfig` is this with theirs."""

    name: str = "curl"
    """Auxiliary self-supervised task (``imssr algos`` lists them)."""
    lr: float = 1e-3
    """Adam learning rate of the auxiliary loss (CURL 1e-3, SODA 3e-4)."""
    update_every: int = 1
    """Agent steps between auxiliary updates."""
    own_batch: bool = False
    """True: the task trains on a batch of its own, ``batch_size`` transitions sampled apart from
    the RL batch (SODA; PAD per Table III); false: on the RL batch itself (CURL)."""
    batch_size: int = 128
    """Size of the task's own batch (Table III: 256 SODA and PAD); unused without ``own_batch``."""


@dataclass
class IntrinsicCore:
    """The settings of the ``intrinsic`` section every signal shares (the reward's normalisation
    and beta schedule); each signal adds its own (its ``*_spec.py``), and
    :class:`imssr.config.IntrinsicConfig` is this with theirs."""

    enabled: bool = False
    """Add ``beta_t * r_int`` to the reward."""
    source: str = "ssl"
    """Where ``r_int`` comes from: ``ssl`` the auxiliary task's per-sample loss of o' (IM-SSR),
    ``rnd`` random network distillation error of o', ``re3`` k-NN distance of o' in a fixed
    random encoder's space.  Chosen by the algo name (``im-X``, ``X+rnd``, ``X+re3``)."""
    beta0: float = 0.0
    """Initial coefficient beta_0 of the intrinsic reward (paper Table V)."""
    schedule: str = "step"
    """``constant`` (beta_t = beta_0) or ``step`` (beta_0 * decay^floor(step / decay_every_steps))."""
    decay: float = 0.8
    """Multiplicative decay of the ``step`` schedule."""
    decay_every_steps: int = 100_000
    """Agent steps between decays of the ``step`` schedule."""
    normalization: str = "zscore"
    """In-batch normalisation of the per-sample losses: zscore, minmax, mean or none."""
    unbiased_std: bool = True
    """``zscore`` divides by the unbiased (n - 1) standard deviation, as the authors' code
    (torch's default ``std``); false: the biased one."""
    norm_eps: float = 0.0
    """Added to the normaliser's denominator (zscore: the std; minmax: the range; mean: the mean).
    IM-CURL 0 (the authors add none), IM-SODA 1e-5 (the authors' ``std + 1e-5``)."""
    norm_rtol: float = 1e-5
    """A batch whose loss spread (std, or max - min) is at most ``norm_rtol * max(|mean|, 1e-12)``
    gets a zero bonus: its differences are float rounding, not novelty.  0: never."""


@dataclass
class TrainConfig:
    steps: int = 500_000
    """Training budget T in agent steps (Table III: 500,000; frames = steps * action_repeat)."""
    seed_steps: int = 1000
    """Agent steps of uniform random actions before learning starts."""
    burst_updates: int = 1000
    """Updates run at the agent step the seed phase ends (DMC-GB and the authors: as many as
    seed steps, 1000); 0 or 1: the usual one.  Only at the end of the first seed phase."""
    replay_capacity: int = 500_000
    """Replay capacity in stored observations, about one per transition (Table III: CURL 100k,
    SODA/PAD/SVEA 500k); an episode of n transitions uses n + 1 slots."""
    eval_every_steps: int = 10_000
    """Agent steps between evaluations (the authors' ``eval_freq``; 0: only at the end)."""
    eval_episodes: int = 30
    """Episodes per evaluation (per scene; the authors' ``eval_episodes``)."""
    eval_modes: str = ""
    """Comma-separated scenes evaluated at each evaluation point; empty: the training scene."""
    checkpoint_every_steps: int = 50_000
    """Agent steps between checkpoints (taken at the next episode end; 0: only at the end)."""
    save_buffer: bool = True
    """Save the replay buffer with each checkpoint (needed for an exact resume)."""
    keep_checkpoints: int = 1
    """Numbered checkpoints kept besides ``latest``."""
    seed: int = 0
    """Seed of the agent, the replay sampler and the training env (eval env uses seed + 10_000)."""
    device: str = "cpu"
    """Torch device: cpu, cuda, cuda:N, or auto."""
    replay_device: str = "auto"
    """Where the replay frames live: ``cpu`` (host memory; on a CUDA agent each batch is gathered
    into pinned memory and copied once), ``cuda`` (a uint8 tensor on the agent's GPU: index, stack
    and crop there), ``disk`` (a file in the run directory on local disk, memory-mapped: the page
    cache keeps what memory allows; for batches whose frames outgrow host memory), or ``auto``
    (the GPU when its free memory holds the frames of every run of the process plus a margin for
    the agents, else the host; docs/performance.md "Replay memory").  The same batches either way."""
    gpu_share: float = 1.0
    """The fraction of its GPU's memory this run may fill, in (0, 1]: below 1 (a sweep's
    ``--gpus-per-run``, runs sharing a GPU), ``replay_device=auto`` counts that fraction of the
    GPU's total memory instead of what is free when the run starts, so that runs started together
    each keep to their share (frames that do not fit it stay on the host)."""
    tensorboard: bool = True
    """Write TensorBoard event files besides the CSV logs."""
    wandb: bool = False
    """Log to Weights & Biases too (the ``wandb`` extra): the config, the scalars TensorBoard gets,
    evaluation videos and the learning curve; ``WANDB_MODE=offline`` keeps it local."""
    wandb_project: str = "imssr"
    """W&B project of the run."""
    wandb_group: str = ""
    """W&B group of the run (``imssr sweep`` sets it to its root's name); empty: none."""
    eval_video_every: int = 0
    """Record one episode per evaluated scene at every k-th evaluation, into
    ``RUN/videos/step_<step>_<mode>.<format>``, TensorBoard and W&B (0: never).  Recording reads
    the frames the evaluation renders anyway: returns and random streams stay the same."""
    eval_video_format: str = "gif"
    """File format of the evaluation videos: gif or mp4."""
    progress: bool = True
    """Show progress: on a terminal a bar with frames per second, else (a log) a line every minute,
    also inside the burst of updates, evaluations, checkpoints and a resume's loading; false: none."""
    torch_threads: int = 0
    """torch intra-op threads (0 leaves torch's default); at most 1024."""
    env_workers: bool = False
    """Step the training env and each evaluation env in a process of its own, overlapped with the
    update where the loop's order allows it (many seeds in one process step all their envs at
    once); the envs see exactly the same calls.  Pays off with ``--seeds`` on a machine with cores
    to spare; costs a process and an EGL context per env."""

    def eval_mode_list(self, training_mode: str) -> list[str]:
        """The scenes to evaluate in, in order, without repeats."""
        modes = [m.strip() for m in self.eval_modes.split(",") if m.strip()] or [training_mode]
        return list(dict.fromkeys(modes))


UPDATE_SCHEDULES = ("sequential", "fused")
PRECISIONS = ("fp32", "bf16")
TF32_MODES = ("default", "true", "false")
COMPILE_MODES = ("off", "default", "max-autotune")
BATCH_LAYOUTS = ("auto", "streams")
"""How a batch of seeds runs (``agent.batch_layout``): both mean the one batch of plain agents."""
STACKED_LAYOUTS = ("vmap", "loop")
"""Layouts of stacked weights that a saved config may name: such a run resumes as the one batch
(:func:`imssr.config.batching.stacked_layout`); a new run asking for one is refused."""
VIDEO_FORMATS = ("gif", "mp4")
REPLAY_DEVICES = ("cpu", "cuda", "auto", "disk")

NORMALIZATIONS = ("zscore", "minmax", "mean", "none")
"""The in-batch normalisations of the intrinsic reward (``intrinsic.normalization``)."""
SCHEDULES = ("constant", "step")
"""The beta schedules of the intrinsic reward (``intrinsic.schedule``)."""


def steps_for_frames(frames: int, action_repeat: int) -> int:
    """Agent steps that cover ``frames`` environment frames (rounded up, as the loop runs them)."""
    return -(-frames // action_repeat)


def conv_output_size(size: int, num_layers: int) -> int:
    """The side of the pixel encoder's output for a ``size`` px input and ``num_layers`` layers
    (``agent.encoder_layers``): the first 3x3 convolution has stride 2, the others stride 1, none
    pads.  Below 1 the layers leave no pixel, which the config refuses."""
    size = (size - 3) // 2 + 1
    return size - 2 * (num_layers - 1)
