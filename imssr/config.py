"""Typed configuration.  Every field documents itself; counters say their unit.

Units: an *agent step* is one action chosen by the agent; it advances the
simulator by ``action_repeat`` *environment frames*.  Every budget, interval and
schedule here counts agent steps, as the authors' code does: the paper's
T = 500,000 agent steps (Table III, "Number of training steps"), which is
4,000,000 frames at action repeat 8.  Replay capacity counts transitions.

``CONFIG_VERSION`` 2 is the format with budgets in agent steps; imssr 0.1's configs
(version 1: budgets in frames) are refused in one line (:func:`check_version`).
"""
from __future__ import annotations

import copy
import dataclasses
import functools
import json
import math
import os
import sys
from dataclasses import dataclass, field, fields
from typing import Any

from docstring_parser import parse_from_object
from omegaconf import OmegaConf
from omegaconf.errors import ConfigKeyError, ValidationError

from imssr.algos import get_algo
from imssr.envs.scenes import get_mode
from imssr.errors import ImssrError
from imssr.jsonio import dumps
from imssr.networks.encoder import conv_output_size

CONFIG_VERSION = 2
"""The config format this imssr reads and writes: budgets in agent steps.  Version 1, imssr 0.1's
(budgets in frames, no ``version`` key), is refused: CHANGELOG.md, 0.2.0, says what its runs need."""
V1_KEYS = (("train", "frames"), ("train", "eval_every_frames"), ("train", "checkpoint_every_frames"),
            ("intrinsic", "view"))
"""Keys only imssr 0.1's configs hold: a file with one of them and no ``version`` is one of those."""

MAX_SEED = 2**31 - 1
"""Largest run seed: numpy's and dm_control's seeds are 32-bit, and evaluation envs use the run
seed + 10,000 and + 20,000, so seeds stay below 2**31 (the sweep's seeds are checked the same)."""
MAX_INT = 2**31 - 1
"""Largest value of any integer setting that has no tighter bound: counts, sizes and intervals
beyond it are typing slips (``1e15``) and would end in an allocation or overflow traceback."""
MAX_IMAGE_SIZE = 480
"""Largest rendered image side: MuJoCo renders offscreen into the models' framebuffer, 640x480 in
every DeepMind Control model (their shared visual settings)."""
MAX_ADDRESSABLE_BYTES = sys.maxsize
"""Largest array a process can address (numpy's limit): bounds the replay buffer's frames."""
SEED_RULE = f"an integer in [0, {MAX_SEED}] (numpy and dm_control take 32-bit seeds, and evaluation adds up to 20000)"


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
    faster and changes pixels by 0.003-0.025 grey levels on average; docs/performance.md)."""


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
    """Random crop (training) / centre crop (acting) size from ``image_size``."""
    discount: float = 0.99
    """Discount factor gamma."""
    batch_size: int = 128
    """RL batch size N."""
    critic_lr: float = 1e-3
    """Adam learning rate of the critic (including the encoder)."""
    critic_beta1: float = 0.9
    """Adam beta1 of the critic."""
    actor_lr: float = 1e-3
    """Adam learning rate of the actor (its head; the convs belong to the critic)."""
    actor_beta1: float = 0.9
    """Adam beta1 of the actor."""
    alpha_lr: float = 1e-4
    """Adam learning rate of the log temperature."""
    alpha_beta1: float = 0.5
    """Adam beta1 of the log temperature."""
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
    tf32: str = "default"
    """TensorFloat-32 on CUDA (about 10 mantissa bits instead of 23; faster on Ampere and later):
    ``default``: PyTorch's own defaults, TF32 in cuDNN convolutions and full float32 matmuls (the
    authors' GPU runs); ``true``: TF32 in matmuls and convolutions; ``false``: strict float32 in
    both.  No effect on CPU."""
    compile: str = "off"
    """``torch.compile`` the conv trunks' passes, projections, Q heads and the actor's layers
    with this mode: ``off``, ``default``, ``reduce-overhead`` or ``max-autotune`` (both CUDA
    graphs on CUDA; each act and update marks a step of them).  The first updates are slow while
    it compiles; needs a C++ compiler on CPU.  Not measured on a GPU."""


@dataclass
class AuxConfig:
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
    tau: float = 0.005
    """EMA rate of the task's own target network (SODA's target encoder and projection)."""
    overlay_alpha: float = 0.5
    """Random overlay ``(1 - alpha) * o + alpha * image`` (SODA)."""
    image_dir: str = ""
    """Folder of natural images (any tree of jpg/png, e.g. Places365) for the overlay; empty:
    ``$IMSSR_IMAGE_DIR`` if set, else the built-in pool made from installed packages' photos."""
    image_pool_size: int = 1024
    """Natural images held in memory for the overlay, drawn from the folder with a fixed seed."""
    svea_alpha: float = 0.5
    """SVEA: weight of the critic loss on the clean observation."""
    svea_beta: float = 0.5
    """SVEA: weight of the critic loss on the random-conv augmented observation."""


@dataclass
class IntrinsicConfig:
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
    rnd_lr: float = 1e-4
    """Adam learning rate of RND's predictor."""
    rnd_dim: int = 128
    """Output size of RND's target and predictor networks."""
    re3_k: int = 3
    """RE3: the k of the k-nearest-neighbour distance within the batch."""
    re3_dim: int = 50
    """RE3: size of the fixed random encoder's output."""
    form: str = "authors"
    """How IM-CURL's and IM-SODA's signal of o' is computed (docs/algorithms.md).  ``authors``:
    as the authors' code did (IM-CURL: online z of the RL crop of o' keyed by the target
    encoder on the same crop; IM-SODA: online predictor on the clean crop vs the target on its
    overlay, squared distance summed over dimensions, then log1p).  ``training``: the task's
    training loss applied to o' (IM-CURL: the key on an independent crop, one more encoder
    pass; IM-SODA: the training loss's orientation, mean over dimensions).  PAD, SVEA, RND and
    RE3 have one form."""


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
    and crop there), or ``auto`` (the GPU when its free memory holds the frames plus a margin for
    the model, else the host; docs/performance.md "Replay memory").  The same batches either way."""
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
    """Show a progress bar with frames per second."""
    torch_threads: int = 0
    """torch intra-op threads (0 leaves torch's default)."""

    def eval_mode_list(self, training_mode: str) -> list[str]:
        """The scenes to evaluate in, in order, without repeats."""
        modes = [m.strip() for m in self.eval_modes.split(",") if m.strip()] or [training_mode]
        return list(dict.fromkeys(modes))


RESUMABLE_CHANGES = frozenset({
    "train.steps", "train.device", "train.replay_device", "train.gpu_share", "train.progress", "train.tensorboard",
    "agent.precision", "agent.tf32", "agent.compile", "train.torch_threads", "train.eval_episodes",
    "train.eval_every_steps", "train.checkpoint_every_steps", "train.eval_modes", "train.save_buffer",
    "train.wandb", "train.wandb_project", "train.wandb_group", "train.eval_video_every",
    "train.eval_video_format"})
"""The settings a resume may change (:meth:`RunConfig.resume_conflicts`): the budget, where and how
fast the run computes, and what it evaluates, logs and keeps; every other setting shapes the
learning and is the run's own."""


@dataclass
class RunConfig:
    algo: str = "im-curl"
    """Algorithm name (``imssr algos``)."""
    version: int = CONFIG_VERSION
    """Config format (see :data:`CONFIG_VERSION`)."""
    env: EnvConfig = field(default_factory=EnvConfig)
    agent: AgentConfig = field(default_factory=AgentConfig)
    aux: AuxConfig = field(default_factory=AuxConfig)
    intrinsic: IntrinsicConfig = field(default_factory=IntrinsicConfig)
    train: TrainConfig = field(default_factory=TrainConfig)

    @property
    def total_steps(self) -> int:
        """Training budget in agent steps (T)."""
        return self.train.steps

    @property
    def total_frames(self) -> int:
        """Training budget in environment frames."""
        return self.train.steps * self.env.action_repeat

    def budget_text(self) -> str:
        """``"500,000 agent steps = 4,000,000 frames at action repeat 8"``."""
        return (f"{self.train.steps:,} agent steps = {self.total_frames:,} frames "
                f"at action repeat {self.env.action_repeat}")

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)

    def resume_conflicts(self, saved: dict[str, Any]) -> list[str]:
        """The settings (dotted names, sorted) in which this config differs from ``saved``, the
        config a run was made with (a checkpoint's or ``config.json``'s object), outside
        :data:`RESUMABLE_CHANGES`: empty when this config may resume the run.  ``saved`` is read
        through this class, so settings added since the run started count as their defaults."""
        try:
            before = _flat(RunConfig.from_dict(saved).to_dict())
        except (ImssrError, TypeError):
            before = _flat(saved)
        now = _flat(self.to_dict())
        return sorted(k for k in before.keys() | now.keys()
                      if before.get(k) != now.get(k) and k not in RESUMABLE_CHANGES)

    def to_json(self) -> str:
        return dumps(self.to_dict(), indent=2, sort_keys=True)

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> "RunConfig":
        """A config from its JSON object (of this version: see :func:`check_version`); fields it
        lacks are the dataclass defaults.  Unknown fields and values of the wrong type are one-line
        errors."""
        if not isinstance(data, dict):
            raise ImssrError(f"a config must be a JSON object, got {type(data).__name__}")
        check_version(data)
        for key, value in data.items():
            if key in SECTIONS and not isinstance(value, dict):
                raise ImssrError(f"config section {key!r} must be an object, got {type(value).__name__}")
        agent = data.get("agent")
        if isinstance(agent, dict) and isinstance(agent.get("tf32"), bool):
            # A JSON boolean agent.tf32 reads as the mode of the same name.
            data = {**data, "agent": {**agent, "tf32": "true" if agent["tf32"] else "false"}}
        return _merged(cls(), data, raw={})

    def validate(self) -> "RunConfig":
        """Reject bad values with one-line errors: the general rules here, each plug-in's beside
        the plug-in (``config_rules`` of every auxiliary task and intrinsic signal)."""
        # The plug-ins are torch modules that import this one for their annotations only: loaded
        # here, the schema imports without them.
        from imssr.auxiliary import AUX_TASKS
        from imssr.intrinsic import INTRINSIC_SIGNALS, IntrinsicReward

        _check_types(self)
        e, a, x, i, t = self.env, self.agent, self.aux, self.intrinsic, self.train
        checks = [
            (e.action_repeat >= 1, "env.action_repeat must be >= 1"),
            (e.frame_stack >= 1, "env.frame_stack must be >= 1"),
            (e.shadow_size >= 1, "env.shadow_size must be >= 1"),
            (0 < a.crop_size <= e.image_size, "agent.crop_size must be in (0, env.image_size]"),
            (a.encoder_layers >= 1, "agent.encoder_layers must be >= 1"),
            (a.encoder_filters >= 1, "agent.encoder_filters must be >= 1"),
            (0 <= a.encoder_head_layers < a.encoder_layers,
             "agent.encoder_head_layers must be in [0, agent.encoder_layers)"),
            (a.crop_size < 3 or conv_output_size(a.crop_size, a.encoder_layers) >= 1,
             f"agent.encoder_layers={a.encoder_layers} leaves no pixels of a {a.crop_size}px crop"),
            (a.feature_dim >= 1, "agent.feature_dim must be >= 1"),
            (a.hidden_dim >= 1, "agent.hidden_dim must be >= 1"),
            (a.log_std_min < a.log_std_max, "agent.log_std_min must be < agent.log_std_max"),
            (0.0 < a.critic_tau <= 1.0 and 0.0 < a.encoder_tau <= 1.0, "agent taus must be in (0, 1]"),
            (min(a.critic_lr, a.actor_lr, a.alpha_lr, x.lr) > 0, "learning rates must be > 0"),
            (a.init_temperature > 0, "agent.init_temperature must be > 0"),
            (min(a.actor_update_every, a.critic_update_every, a.target_update_every) >= 1,
             "agent update intervals must be >= 1"),
            (x.batch_size >= 2, "aux.batch_size must be >= 2"),
            (a.batch_size >= 2, "agent.batch_size must be >= 2"),
            (0.0 <= a.discount <= 1.0, "agent.discount must be in [0, 1]"),
            (a.update_schedule in UPDATE_SCHEDULES,
             f"agent.update_schedule must be one of {', '.join(UPDATE_SCHEDULES)}"),
            (a.update_schedule != "fused" or a.critic_update_every == 1,
             "agent.update_schedule=fused needs agent.critic_update_every=1"),
            (a.precision in PRECISIONS, f"agent.precision must be one of {', '.join(PRECISIONS)}"),
            (a.tf32 in TF32_MODES, f"agent.tf32 must be one of {', '.join(TF32_MODES)}"),
            (a.compile in COMPILE_MODES, f"agent.compile must be one of {', '.join(COMPILE_MODES)}"),
            (x.update_every >= 1, "aux.update_every must be >= 1"),
            (i.source in INTRINSIC_SIGNALS, f"intrinsic.source must be one of {', '.join(INTRINSIC_SIGNALS)}"),
            # Each auxiliary task and signal checks its own settings, the intrinsic reward its
            # normalisation and schedule.
            *(rule for plugin in (*AUX_TASKS.values(), *INTRINSIC_SIGNALS.values(), IntrinsicReward)
              for rule in plugin.config_rules(self)),
            (self.version == CONFIG_VERSION, f"version must be {CONFIG_VERSION}"),
            (t.steps >= 1, "train.steps must be >= 1"),
            (t.seed_steps >= 1, "train.seed_steps must be >= 1 (the first update needs a transition)"),
            (t.burst_updates >= 0, "train.burst_updates must be >= 0"),
            (t.torch_threads >= 0, "train.torch_threads must be >= 0"),
            (t.keep_checkpoints >= 0, "train.keep_checkpoints must be >= 0"),
            (t.replay_capacity >= 2, "train.replay_capacity must be >= 2"),
            (t.replay_device in REPLAY_DEVICES,
             f"train.replay_device must be one of {', '.join(REPLAY_DEVICES)}, got {t.replay_device!r}"),
            (0 < t.gpu_share <= 1, f"train.gpu_share must be in (0, 1], got {t.gpu_share}"),
            (t.eval_every_steps >= 0, "train.eval_every_steps must be >= 0"),
            (t.eval_episodes >= 1, "train.eval_episodes must be >= 1"),
            (t.checkpoint_every_steps >= 0, "train.checkpoint_every_steps must be >= 0"),
            (t.eval_video_every >= 0, "train.eval_video_every must be >= 0"),
            (t.eval_video_format in VIDEO_FORMATS,
             f"train.eval_video_format must be one of {', '.join(VIDEO_FORMATS)}"),
            (bool(t.wandb_project.strip()), "train.wandb_project must not be empty"),
            (0 <= t.seed <= MAX_SEED, f"train.seed must be {SEED_RULE}, got {t.seed}"),
        ]
        for ok, message in checks:
            if not ok:
                raise ImssrError(message)
        self._check_upper_bounds()
        for mode in [e.mode, *t.eval_mode_list(e.mode)]:
            get_mode(mode)
        if e.footage_dir and not os.path.exists(os.path.expanduser(e.footage_dir)):
            raise ImssrError(f"footage not found: {e.footage_dir} (env.footage_dir / --footage)")
        algo = get_algo(self.algo)
        if algo.aux != x.name or algo.intrinsic_enabled != i.enabled or \
                (algo.intrinsic_enabled and algo.intrinsic != i.source):
            raise ImssrError(f"algo {self.algo} means aux.name={algo.aux}, intrinsic.enabled="
                             f"{str(algo.intrinsic_enabled).lower()}"
                             + (f", intrinsic.source={algo.intrinsic}" if algo.intrinsic_enabled else "")
                             + "; choose the algo instead of overriding these")
        return self

    def _check_upper_bounds(self) -> None:
        """Integers bounded from above: the replay buffer by what a process can address, the image
        by the renderer, every other integer by :data:`MAX_INT` (layer counts are bounded by the
        crop they must leave pixels of, in :meth:`validate`)."""
        e, t = self.env, self.train
        frame_bytes = 3 * e.image_size * e.image_size
        if t.replay_capacity > MAX_ADDRESSABLE_BYTES // frame_bytes:
            raise ImssrError(f"train.replay_capacity={t.replay_capacity} needs {t.replay_capacity * frame_bytes:.3g} "
                             f"bytes of {e.image_size}px frames, more than a process can address; "
                             "lower the replay capacity")
        if e.image_size > MAX_IMAGE_SIZE:
            raise ImssrError(f"env.image_size must be at most {MAX_IMAGE_SIZE} (the offscreen framebuffer of "
                             f"the suite's models is 640x{MAX_IMAGE_SIZE}), got {e.image_size}")
        for key, kind in FIELD_TYPES.items():
            if kind is int and key != "train.seed" and _get(self, key) > MAX_INT:
                raise ImssrError(f"{key} must be at most {MAX_INT:,}, got {_get(self, key)}")


UPDATE_SCHEDULES = ("sequential", "fused")
PRECISIONS = ("fp32", "bf16")
TF32_MODES = ("default", "true", "false")
COMPILE_MODES = ("off", "default", "reduce-overhead", "max-autotune")
VIDEO_FORMATS = ("gif", "mp4")
REPLAY_DEVICES = ("cpu", "cuda", "auto")


LOGGERS = ("csv", "tensorboard", "wandb")
"""The names ``--logger`` takes; CSV logs are written whatever it says."""


def logger_fields(text: str, no_tensorboard: bool = False) -> dict[str, bool]:
    """``--logger csv,tensorboard,wandb`` as the config fields it sets (``train.tensorboard``,
    ``train.wandb``); ``no_tensorboard``: ``--no-tensorboard`` was given too."""
    names = [n.strip() for n in text.split(",") if n.strip()]
    unknown = [n for n in names if n not in LOGGERS]
    if unknown:
        raise ImssrError(f"unknown logger {unknown[0]!r} in --logger; choose from {', '.join(LOGGERS)}")
    if no_tensorboard and "tensorboard" in names:
        raise ImssrError("--no-tensorboard and --logger ...tensorboard contradict each other; give one")
    return {"train.tensorboard": "tensorboard" in names, "train.wandb": "wandb" in names}


def steps_for_frames(frames: int, action_repeat: int) -> int:
    """Agent steps that cover ``frames`` environment frames (rounded up, as the loop runs them)."""
    return -(-frames // action_repeat)


def check_version(data: dict[str, Any], source: str = "this config") -> None:
    """Refuse, in one line, a config dict of another format than :data:`CONFIG_VERSION`: imssr
    0.1's (``version`` 1, or none and a key of :data:`V1_KEYS`), or an unknown version.  A dict
    without ``version`` and without those keys is a partial config written by hand for this one."""
    version = data.get("version")
    if version is None and any(isinstance(data.get(section), dict) and key in data[section]
                               for section, key in V1_KEYS):
        version = 1
    if version == 1 and not isinstance(version, bool):
        raise ImssrError(f"{source} is an imssr 0.1 config (budgets in frames), which this imssr does not "
                         "read: re-run the run, or evaluate it with imssr 0.1 (CHANGELOG.md, 0.2.0)")
    if version is not None and (version != CONFIG_VERSION or isinstance(version, bool)):
        raise ImssrError(f"{source} has config version {version!r}; this imssr reads version {CONFIG_VERSION}")


# -- types and overrides, through OmegaConf structured configs ---------------------------------
# OmegaConf holds the dataclasses' schema: it rejects unknown keys and values it cannot convert
# to a field's type.  imssr adds what OmegaConf allows and a run must not: NaN and infinity.
SECTIONS = {"env": EnvConfig, "agent": AgentConfig, "aux": AuxConfig, "intrinsic": IntrinsicConfig,
            "train": TrainConfig}
"""Config sections and their dataclasses, in the order of :class:`RunConfig`."""
FIELD_TYPES = {"algo": str, "version": int, **{f"{name}.{f.name}": type(getattr(cls(), f.name))
                                                for name, cls in SECTIONS.items() for f in fields(cls)}}
"""``section.field`` (and the top-level ``algo``, ``version``) -> its type: bool, int, float or str."""
TYPE_WORDS = {bool: "true or false", int: "an integer", float: "a number", str: "a string"}


def _merged(cfg: RunConfig, data: dict[str, Any], raw: dict[str, str]) -> RunConfig:
    """``cfg`` with the (nested) ``data`` merged on by OmegaConf; ``raw`` maps an override's
    dotted key to its text, for errors that quote what was typed.  Text is taken as it is
    (:func:`_set_aside_text`)."""
    base, data, texts = _set_aside_text(cfg, data, raw)
    try:
        merged = OmegaConf.to_object(OmegaConf.merge(OmegaConf.structured(base), data))
    except ConfigKeyError as exc:  # also ConfigAttributeError
        section, _, name = str(exc.full_key).partition(".")
        if not name:
            raise ImssrError(f"unknown config section {section!r}") from None
        raise ImssrError(f"unknown setting {exc.full_key!r}; {section} has: "
                         f"{', '.join(sorted(f.name for f in fields(SECTIONS[section])))}") from None
    except (ValidationError, OverflowError) as exc:
        # OverflowError: an integer too large for a float field (no key attached).
        key = getattr(exc, "full_key", None) or _overflowing(data)
        value = getattr(exc, "value", None)
        if isinstance(exc, OverflowError) and key not in raw:
            raise ImssrError(f"{key} must be a finite number, got an integer too large for a float") from None
        if key in raw:
            raise ImssrError(f"{key} expects {_expected(key)}, got {raw[key]!r}") from None
        raise ImssrError(f"{key} must be a {FIELD_TYPES.get(key, str).__name__}, got {value!r}") from None
    for key, text in texts.items():
        _set(merged, key, text)
    for key, text in raw.items():
        if FIELD_TYPES[key] is float and not _is_finite(_get(merged, key)):
            raise ImssrError(f"{key} expects a finite number, got {text!r}")
    return merged


def _set_aside_text(cfg: RunConfig, data: dict[str, Any], raw: dict[str, str]
                    ) -> tuple[RunConfig, dict[str, Any], dict[str, str]]:
    """``cfg`` and ``data`` with the text of their string fields taken out, and that text by
    dotted key, to be put back after the merge.

    Config values are data: OmegaConf reads ``${...}`` in a value as an interpolation (``${oc.env:
    NAME}`` would copy an environment variable, a secret, into config.json and the checkpoint) and
    ``???`` as "missing".  A string field needs no conversion, so its text never reaches OmegaConf
    and stays as written; such text in a field of another type is refused."""
    texts: dict[str, str] = {}
    base = copy.deepcopy(cfg)
    for key, kind in FIELD_TYPES.items():
        value = _get(cfg, key)
        if isinstance(value, str) and kind is str:
            texts[key] = value
            _set(base, key, "")
        elif isinstance(value, str) and _interpolated(value):
            raise ImssrError(f"{key} expects {_expected(key)}, got {value!r}")
    rest: dict[str, Any] = {}
    for name, value in data.items():
        if name in SECTIONS and isinstance(value, dict):
            rest[name] = {}
            for field_name, item in value.items():
                if _text_of(f"{name}.{field_name}", item, raw, texts):
                    rest[name][field_name] = item
        elif _text_of(name, value, raw, texts):
            rest[name] = value
    return base, rest, texts


def _text_of(key: str, value: Any, raw: dict[str, str], texts: dict[str, str]) -> bool:
    """Whether ``value`` of ``key`` goes to OmegaConf; the text of a string field goes into
    ``texts`` instead.  Text that OmegaConf would interpret is refused for other fields."""
    kind = FIELD_TYPES.get(key)
    if isinstance(value, str) and kind is str:
        texts[key] = value
        return False
    if kind is str:
        # Another value for a string field (``"device": 5``) is converted or refused by
        # OmegaConf, and the field's rules judge what it became: the base's text must not be
        # put back over it.
        texts.pop(key, None)
        return True
    if isinstance(value, str) and kind is not None and _interpolated(value):
        raise ImssrError(f"{key} expects {_expected(key)}, got {raw.get(key, value)!r}")
    return True


def _interpolated(text: str) -> bool:
    """Whether OmegaConf would read ``text`` as something other than itself."""
    return "${" in text or text == "???"


def _expected(key: str) -> str:
    kind = FIELD_TYPES.get(key, str)
    return "a finite number" if kind is float else TYPE_WORDS[kind]


def _overflowing(data: dict[str, Any]) -> str:
    """The first ``section.field`` of ``data`` that holds an integer too large for a float
    (OmegaConf's OverflowError names none)."""
    for section, values in data.items():
        for name, value in (values.items() if isinstance(values, dict) else ()):
            if isinstance(value, int) and FIELD_TYPES.get(f"{section}.{name}") is float and not _is_finite(value):
                return f"{section}.{name}"
    return "a config value"


def _flat(d: dict[str, Any], prefix: str = "") -> dict[str, Any]:
    """A nested dict's leaves under their dotted names."""
    out: dict[str, Any] = {}
    for k, v in d.items():
        out.update(_flat(v, f"{prefix}{k}.") if isinstance(v, dict) else {f"{prefix}{k}": v})
    return out


def _get(cfg: RunConfig, key: str) -> Any:
    section, _, name = key.rpartition(".")
    return getattr(getattr(cfg, section) if section else cfg, name)


def _set(cfg: RunConfig, key: str, value: Any) -> None:
    section, _, name = key.rpartition(".")
    setattr(getattr(cfg, section) if section else cfg, name, value)


def _check_types(cfg: RunConfig) -> None:
    """Reject values of the wrong type (e.g. set in code, or from a hand-edited JSON file): a
    value OmegaConf refuses or would have to convert (``"5"`` for an int, ``1`` for a bool), and
    NaN or infinity, which pass every comparison check or break them and end a run only later,
    in a simulator traceback."""
    for key, kind in FIELD_TYPES.items():
        value = _get(cfg, key)
        if kind is float and isinstance(value, (int, float)) and not _is_finite(value):
            raise ImssrError(f"{key} must be a finite number, got {value!r}")
    typed = _merged(cfg, {}, raw={})
    for key, kind in FIELD_TYPES.items():
        value = _get(cfg, key)
        if _get(typed, key) != value or isinstance(value, bool) != (kind is bool):
            raise ImssrError(f"{key} must be a {kind.__name__}, got {value!r}")


def _is_finite(value) -> bool:
    try:
        return math.isfinite(value)
    except OverflowError:  # an integer too large for a float
        return False


def apply_overrides(cfg: RunConfig, overrides: list[str]) -> RunConfig:
    """``cfg`` with ``section.field=value`` strings applied (the CLI's ``--set``).

    A value is converted to its field's type by OmegaConf (``64``, ``1e-3``, ``true``); a
    JSON string (``"a b"``) is unquoted; anything else is the text itself.
    """
    data: dict[str, dict[str, Any]] = {}
    raw: dict[str, str] = {}
    for item in overrides:
        if "=" not in item or "." not in item.split("=", 1)[0]:
            raise ImssrError(f"override {item!r} must look like section.field=value")
        key, text = item.split("=", 1)
        section, name = key.split(".", 1)
        if section not in SECTIONS:
            raise ImssrError(f"unknown config section {section!r} in override {item!r}")
        data.setdefault(section, {})[name] = _override_value(key, text)
        raw[key] = text
    return _merged(cfg, data, raw)


def _override_value(key: str, text: str) -> Any:
    """What OmegaConf gets for ``key=text``: the text itself, except a JSON string (unquoted)
    and, for an integer field, a JSON number with an integral value (``1e3``, ``64.0``)."""
    try:
        value = json.loads(text)
    except json.JSONDecodeError:
        return text
    if isinstance(value, str):
        return value
    if FIELD_TYPES.get(key) is int and isinstance(value, float) and math.isfinite(value) and value.is_integer():
        return int(value)
    return text


@functools.cache
def field_docs() -> dict[str, str]:
    """``section.field`` -> the field's docstring (whitespace collapsed), read once from the
    dataclasses' source: the CLI's help texts use them.  Empty when installed without sources."""
    return {f"{section}.{doc.arg_name}": " ".join(doc.description.split())
            for section, cls in SECTIONS.items() for doc in parse_from_object(cls).params
            if doc.args[0] == "attribute" and doc.description}


def read_config_file(path: str) -> Any:
    """The JSON value of a config file, with one-line errors for anything that is not JSON text."""
    try:
        with open(path, encoding="utf-8") as fh:
            return json.load(fh)
    except FileNotFoundError:
        raise ImssrError(f"config file not found: {path}") from None
    except IsADirectoryError:
        raise ImssrError(f"config file {path} is a directory") from None
    except UnicodeDecodeError:
        raise ImssrError(f"config file {path} is not a JSON text file (it is not UTF-8 text)") from None
    except json.JSONDecodeError as exc:
        raise ImssrError(f"config file {path} is not valid JSON: {exc}") from None


def load_config(path: str) -> RunConfig:
    """A complete config file, such as a run's ``config.json`` (fields it lacks read as the
    dataclass defaults; see :func:`load_partial_config` for a file written by hand)."""
    data = read_config_file(path)
    if isinstance(data, dict):
        check_version(data, f"config {path}")
    return RunConfig.from_dict(data)
