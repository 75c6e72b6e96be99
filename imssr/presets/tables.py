"""The paper's settings, each with its source: the rows every preset is made of.

Where each value comes from: the authors' code (``duchenzhuang/dmc-disentangle``, a fork of
DMC-GB that produced the paper's numbers) where the paper's tables are silent, Table III and
Table V where they speak.  :func:`preset_settings` gathers the rows of one algorithm on one task
(docs/provenance.md prints them all, ``imssr config --explain`` one preset's);
:mod:`imssr.presets.build` makes configs of them.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

from imssr.algos import AlgoSpec, get_algo
from imssr.config import RunConfig
from imssr.envs.tasks import get_task
from imssr.errors import ImssrError


# Table V: beta_0 per task (../shared/spec/paper_beta0.csv; tests check the copy).
PAPER_BETA0 = {
    "curl": {"cartpole_swingup_sparse": 0.01, "finger_spin": 0.005, "pendulum_swingup": 0.05,
             "reacher_easy": 0.005, "walker_walk": 0.005, "walker_walk_sparse": 0.1},
    "soda": {"cartpole_swingup_sparse": 0.01, "finger_spin": 0.005, "pendulum_swingup": 0.1,
             "reacher_easy": 0.001, "walker_walk": 0.05, "walker_walk_sparse": 0.1},
}
# IM-PAD and IM-SVEA: the paper reports beta_0 = 0.05 (on pendulum_swingup) and no other value.
BASE_BETA0 = {"pad": 0.05, "svea": 0.05}
# beta_0 for tasks outside Table V: the paper's most common small value.
DEFAULT_BETA0 = 0.01
# The paper's text keeps beta fixed on this task and decays it (x0.8 / 100k steps) elsewhere;
# the authors' IM-CURL script decays it there too (see SCHEDULE).
CONSTANT_BETA_TASKS = ("cartpole_swingup_sparse",)


def paper_beta0(algo: str, task: str) -> float:
    """beta_0 for ``algo`` on ``task``: Table V for IM-CURL / IM-SODA, 0.05 for IM-PAD / IM-SVEA.

    RND and RE3 use the IM- variant's value of the same base, so a comparison
    changes only the signal.
    """
    base = get_algo(algo).base
    if base in PAPER_BETA0:
        return PAPER_BETA0[base].get(task, DEFAULT_BETA0)
    return BASE_BETA0.get(base, DEFAULT_BETA0)


# -- provenance ---------------------------------------------------------------------------
# Where each preset value comes from.  The authors' code is duchenzhuang/dmc-disentangle
# (a fork of DMC-GB that produced the paper's numbers); Table III wins where it speaks.
TABLE3 = "Table III"
TABLE5 = "Table V"
PAPER = "paper, Appendix (Implementation Details)"
AUTHORS = "authors' code (arguments.py default)"
AUTHORS_LOOP = "authors' code (train.py)"
AUTHORS_CURL = "authors' scripts/curl/*.sh (DMC-GB CURL)"
AUTHORS_SIGNAL = "authors' code (intrinsic reward)"
DMCGB = "DMC-GB"
OFFICIAL_CURL = "official CURL"
IMSSR = "imssr"


@dataclass(frozen=True)
class Setting:
    """One preset value and where it comes from."""

    field: str
    """Dotted config field, ``section.name``."""
    value: object
    source: str
    note: str = ""
    """Why, where the value deviates from the authors' code or needs a word."""

    @property
    def deviation(self) -> bool:
        return bool(self.note) and self.note.startswith("deviation")


RUN = "run setting"
RUN_FIELDS = ("env.footage_dir", "aux.image_dir", "aux.image_pool_size", "train.save_buffer",
              "train.keep_checkpoints", "train.device", "train.replay_device", "train.gpu_share",
              "train.tensorboard", "train.progress", "train.torch_threads", "train.wandb", "train.wandb_project",
              "train.wandb_group", "train.eval_video_every", "train.eval_video_format", "train.env_workers")
"""Fields that say where data comes from or how a run is kept and shown, not what it learns."""

COMMON = (
    Setting("env.image_size", 100, TABLE3, "rendered 100x100, cropped to 84"),
    Setting("env.frame_stack", 3, TABLE3),
    Setting("env.mode", "training", AUTHORS, "the scene the agent trains in"),
    Setting("env.shadow_size", 512, IMSSR, "deviation: dm_control renders 2048-px shadow maps; 512 "
            "steps the env ~2x faster and moves pixels by 0.003-0.025 grey levels on average "
            "(docs/performance.md); --set env.shadow_size=2048 restores it"),
    Setting("agent.crop_size", 84, TABLE3),
    Setting("agent.encoder_filters", 32, TABLE3),
    Setting("agent.final_relu", False, DMCGB, "DMC-GB's encoder has no ReLU after its last "
            "convolution (official CURL has one: --network official-curl)"),
    Setting("agent.feature_dim", 100, AUTHORS, "projection_dim; official CURL: 50"),
    Setting("agent.projection_tanh", True, DMCGB, "RLProjection: Linear -> LayerNorm -> Tanh"),
    Setting("agent.hidden_dim", 1024, AUTHORS),
    Setting("agent.discount", 0.99, TABLE3),
    Setting("agent.batch_size", 128, TABLE3),
    Setting("agent.critic_lr", 1e-3, TABLE3),
    Setting("agent.critic_beta1", 0.9, TABLE3),
    Setting("agent.actor_lr", 1e-3, TABLE3),
    Setting("agent.actor_beta1", 0.9, TABLE3),
    Setting("agent.alpha_lr", 1e-4, TABLE3),
    Setting("agent.alpha_beta1", 0.5, TABLE3),
    Setting("agent.init_temperature", 0.1, AUTHORS),
    Setting("agent.critic_tau", 0.01, AUTHORS),
    Setting("agent.encoder_tau", 0.05, AUTHORS),
    Setting("agent.actor_update_every", 2, TABLE3),
    Setting("agent.critic_update_every", 1, TABLE3),
    Setting("agent.target_update_every", 2, AUTHORS),
    Setting("agent.log_std_min", -10.0, AUTHORS),
    Setting("agent.log_std_max", 2.0, AUTHORS),
    Setting("agent.update_schedule", "sequential", AUTHORS_LOOP,
            "critic, actor + temperature, targets, auxiliary task, in that order"),
    Setting("agent.channels_last", True, IMSSR, "memory layout only: the same maths"),
    Setting("agent.precision", "fp32", AUTHORS_LOOP, "every pass in float32"),
    Setting("agent.q_heads_fp32", False, IMSSR, "a bf16 setting: no effect at fp32"),
    Setting("agent.tf32", "default", AUTHORS_LOOP, "PyTorch's defaults, as the authors' GPU runs had: "
            "TF32 in cuDNN convolutions, full float32 matmuls (CUDA only; "
            "`false`: strict float32)"),
    Setting("agent.compile", "off", AUTHORS_LOOP, "eager PyTorch"),
    Setting("agent.fused_adam", False, AUTHORS_LOOP, "torch's default Adam (foreach kernels on CUDA)"),
    Setting("train.steps", 500_000, TABLE3, "T = 500,000 agent steps ('Number of training "
            "steps'; the authors' train_steps); the paper's text says 'frames'"),
    Setting("train.seed_steps", 1000, AUTHORS, "init_steps: uniform random actions"),
    Setting("train.burst_updates", 1000, AUTHORS_LOOP, "init_steps updates at the step the "
            "seed phase ends"),
    Setting("train.eval_every_steps", 10_000, AUTHORS, "eval_freq"),
    Setting("train.eval_episodes", 30, AUTHORS, "eval_episodes"),
    Setting("train.eval_modes", "", IMSSR, "deviation: the authors also evaluate four test scenes "
            "at each point (color_easy, color_hard, video_easy, video_hard; DMC-GB itself one); "
            "add them with --eval-modes training,color_easy,color_hard,video_easy,video_hard"),
    Setting("train.checkpoint_every_steps", 50_000, IMSSR, "resumable checkpoints (the authors "
            "save weights every 100k steps)"),
    Setting("train.seed", 0, "user"),
    Setting("intrinsic.enabled", False, "algo", "true for im-X, X+rnd, X+re3"),
    # Run settings: they do not change what is learned; their values are the schema's defaults.
    *(Setting(f, getattr(getattr(RunConfig(), f.split(".")[0]), f.split(".")[1]), RUN) for f in RUN_FIELDS),
)
"""Settings every algorithm shares (the SAC core, the loop, the budget), after the algo, the task
and its action repeat."""

BASE_SETTINGS = {
    "curl": (
        Setting("agent.encoder_layers", 4, TABLE3, "num_shared_layers 4 in the authors' scripts"),
        Setting("agent.encoder_head_layers", 0, AUTHORS_CURL),
        Setting("aux.name", "curl", "algo"),
        Setting("aux.lr", 1e-3, AUTHORS, "aux_lr"),
        Setting("aux.update_every", 1, TABLE3, "aux_update_freq 1 in the authors' scripts"),
        Setting("aux.own_batch", False, AUTHORS_CURL, "CURL trains on the RL batch (Table III: SSL "
                "batch 128 = RL batch)"),
        Setting("aux.batch_size", 128, TABLE3, "unused: CURL trains on the RL batch"),
        Setting("train.replay_capacity", 100_000, TABLE3, "deviation from the authors' scripts "
                "(--capacity 200k): Table III wins"),
    ),
    "soda": (
        Setting("agent.encoder_layers", 11, TABLE3),
        Setting("agent.encoder_head_layers", 0, DMCGB),
        Setting("aux.name", "soda", "algo"),
        Setting("aux.lr", 3e-4, TABLE3),
        Setting("aux.update_every", 2, TABLE3, "also the parser default of the authors' SODA "
                "with the intrinsic reward (1 in some of their other commits)"),
        Setting("aux.own_batch", True, DMCGB, "sampled apart from the RL batch"),
        Setting("aux.batch_size", 256, TABLE3),
        Setting("aux.tau", 0.005, TABLE3),
        Setting("aux.overlay_alpha", 0.5, DMCGB),
        Setting("train.replay_capacity", 500_000, TABLE3),
    ),
    "pad": (
        Setting("agent.encoder_layers", 11, TABLE3),
        Setting("agent.encoder_head_layers", 3, DMCGB, "8 shared + 3 head layers"),
        Setting("aux.name", "pad", "algo"),
        Setting("aux.lr", 1e-3, DMCGB, "aux_lr"),
        Setting("aux.update_every", 1, TABLE3, "deviation from DMC-GB and the authors' code (every "
                "2nd agent step, their parser default; their pad.sh sets nothing): Table III wins"),
        Setting("aux.own_batch", True, TABLE3, "deviation from DMC-GB (PAD on the RL batch of "
                "128): Table III gives PAD an SSL batch of 256"),
        Setting("aux.batch_size", 256, TABLE3),
        Setting("train.replay_capacity", 500_000, TABLE3),
    ),
    "svea": (
        Setting("agent.encoder_layers", 11, TABLE3),
        Setting("agent.encoder_head_layers", 0, DMCGB),
        Setting("aux.name", "svea", "algo"),
        Setting("aux.svea_alpha", 0.5, DMCGB),
        Setting("aux.svea_beta", 0.5, DMCGB),
        Setting("train.replay_capacity", 500_000, TABLE3),
    ),
}
"""Settings of each base algorithm (its auxiliary task and networks)."""

# The authors' CURL scripts pass --in_decay 0.8 on every task, cartpole included; where text and
# code differ and no table speaks, their code wins.  No script of the authors' reproduces an
# IM-SODA (or IM-PAD, IM-SVEA) run of the paper's tables, so the paper's text gives theirs.
DECAY = "x0.8 every 100k agent steps"
SCHEDULE = {
    "curl": Setting("intrinsic.schedule", "step", AUTHORS_CURL, DECAY),
    **{base: Setting("intrinsic.schedule", "step", PAPER, DECAY) for base in ("soda", "pad", "svea")},
}
"""The beta schedule of each base's intrinsic reward, on a task outside :data:`CONSTANT_BETA_TASKS`."""
CONSTANT_BETA_SCHEDULE = {
    "curl": Setting("intrinsic.schedule", "step", AUTHORS_CURL, "deviation from the paper's text (beta "
                    "fixed on cartpole_swingup_sparse): the authors' script decays it; --set "
                    "intrinsic.schedule=constant gives the text's"),
    **{base: Setting("intrinsic.schedule", "constant", PAPER, "beta fixed on cartpole_swingup_sparse")
       for base in ("soda", "pad", "svea")},
}
"""The beta schedule of each base's intrinsic reward on the tasks of :data:`CONSTANT_BETA_TASKS`."""

INTRINSIC = (
    Setting("intrinsic.decay", 0.8, PAPER, "the authors' in_decay"),
    Setting("intrinsic.decay_every_steps", 100_000, PAPER, "agent steps (the authors' update step)"),
    Setting("intrinsic.normalization", "zscore", AUTHORS_SIGNAL),
    Setting("intrinsic.unbiased_std", True, AUTHORS_SIGNAL, "torch's default std"),
)
"""Settings every intrinsic reward shares, after its signal, beta_0 and schedule (then its
base's :data:`NORM_EPS`, then :data:`INTRINSIC_LAST`)."""

# Normalisation of the signal per base, as the authors' code computes it (IM-CURL, IM-SODA);
# IM-PAD and IM-SVEA have no code of the authors and follow IM-CURL's.
NORM_EPS = {
    "curl": Setting("intrinsic.norm_eps", 0.0, AUTHORS_SIGNAL, "z-score with the unbiased std, nothing added"),
    "soda": Setting("intrinsic.norm_eps", 1e-5, AUTHORS_SIGNAL, "z-score with std + 1e-5"),
    "pad": Setting("intrinsic.norm_eps", 0.0, IMSSR, "no code of the authors: as IM-CURL"),
    "svea": Setting("intrinsic.norm_eps", 0.0, IMSSR, "no code of the authors: as IM-CURL"),
}

INTRINSIC_LAST = (
    Setting("intrinsic.norm_rtol", 1e-5, IMSSR, "a batch of equal losses gets a zero bonus, not "
            "its rounding error divided by a tiny std"),
    Setting("intrinsic.form", "authors", AUTHORS_SIGNAL, "IM-CURL, IM-SODA: as the authors "
            "computed the signal (docs/algorithms.md); 'training' keeps the training loss's form"),
)
"""Settings every intrinsic reward shares, after its base's :data:`NORM_EPS`."""

SIGNAL_SETTINGS = {
    "ssl": (),
    "rnd": (Setting("intrinsic.rnd_lr", 1e-4, "RND (Burda et al. 2018)"),
            Setting("intrinsic.rnd_dim", 128, IMSSR, "RND's output size")),
    "re3": (Setting("intrinsic.re3_k", 3, "RE3 (Seo et al. 2021)"),
            Setting("intrinsic.re3_dim", 50, "RE3 (Seo et al. 2021)")),
}
"""Settings of each intrinsic signal's own networks."""

# Where the authors' scripts pass another in_gamma than Table V (Table V wins).
SCRIPT_BETA0 = {("curl", "pendulum_swingup"): "deviation from the authors' script (--in_gamma 0.01): "
                "Table V wins",
                ("curl", "reacher_easy"): "deviation from the authors' script (--in_gamma 0.001): "
                "Table V wins",
                ("curl", "walker_walk"): "deviation from the authors' script (--in_gamma 0.05 in its "
                "commented-out lines, which also turn the intrinsic reward on): Table V wins",
                ("soda", "finger_spin"): "deviation from the authors' finger_spin SODA scripts "
                "(scripts/nips/soda_finger_*.sh run in_gamma 0.001 to 10.0, 1.0 among them): "
                "Table V wins"}


def _beta0(spec: AlgoSpec, task: str) -> Setting:
    """beta_0 of ``spec`` on ``task`` (:func:`paper_beta0`) with its source."""
    base, value = spec.base, paper_beta0(spec.name, task)
    if base in PAPER_BETA0 and task in PAPER_BETA0[base]:
        source = TABLE5
    elif base in BASE_BETA0:
        source = "paper (beta_0 = 0.05 for IM-PAD / IM-SVEA)"
    else:
        return Setting("intrinsic.beta0", value, IMSSR, f"no value in the paper for {task}: {DEFAULT_BETA0}")
    note = "the IM- variant's value, so that only the signal changes" if spec.intrinsic != "ssl" else \
        SCRIPT_BETA0.get((base, task), "")
    return Setting("intrinsic.beta0", value, source, note)


NETWORKS = {
    "dmcgb": (),
    "official-curl": (
        Setting("agent.feature_dim", 50, OFFICIAL_CURL, "encoder_feature_dim"),
        Setting("agent.projection_tanh", False, OFFICIAL_CURL, "LayerNorm output, no tanh"),
        Setting("agent.final_relu", True, OFFICIAL_CURL, "ReLU after every convolution"),
    ),
}
"""Encoder layouts: ``dmcgb`` (what the authors ran, every preset's default) and
``official-curl`` (the CURL paper's code), for people comparing with the CURL paper."""


def preset_settings(algo: str, task: str, network: str = "dmcgb") -> list[Setting]:
    """Every value the preset of ``algo`` on ``task`` sets, with its source, in order.

    A later setting of the same field wins (the intrinsic reward's and the network's over the
    common ones).
    """
    spec = get_algo(algo)
    tspec = get_task(task)
    if network not in NETWORKS:
        raise ImssrError(f"unknown network {network!r}; valid: {', '.join(NETWORKS)}")
    rows = [Setting("algo", spec.name, "user"), Setting("env.task", tspec.name, "user"),
            Setting("env.action_repeat", tspec.action_repeat, TABLE3), *COMMON, *BASE_SETTINGS[spec.base]]
    if spec.intrinsic_enabled:
        schedule = (CONSTANT_BETA_SCHEDULE if tspec.name in CONSTANT_BETA_TASKS else SCHEDULE)[spec.base]
        rows += [Setting("intrinsic.enabled", True, "algo"), Setting("intrinsic.source", spec.intrinsic, "algo"),
                 _beta0(spec, tspec.name), schedule, *INTRINSIC, NORM_EPS[spec.base], *INTRINSIC_LAST,
                 *SIGNAL_SETTINGS[spec.intrinsic]]
    rows += NETWORKS[network]
    merged: dict[str, Setting] = {}
    for row in rows:
        merged.pop(row.field, None)
        merged[row.field] = row
    return list(merged.values())


DEMO = (
    Setting("agent.batch_size", 64, "demo", "also the auxiliary batch of a task that trains on the RL batch"),
    Setting("agent.update_schedule", "fused", "demo", "one encoder pass and one backward for critic + "
            "CURL: 0.8x the sequential step"),
    Setting("train.steps", 1000, "demo", "8 episodes, 1,000 updates: 6x-29x the untrained return at "
            "the last evaluation in seeds 0-2 at 2 threads, >= 3x in 5 of 6 seeded runs; 8-13 min on 2 cores"),
    Setting("train.seed_steps", 250, "demo"),
    Setting("train.burst_updates", 250, "demo", "as many as seed steps, as in the authors' loop"),
    Setting("train.eval_every_steps", 250, "demo"),
    Setting("train.eval_episodes", 5, "demo"),
    Setting("train.checkpoint_every_steps", 500, "demo"),
)
"""The demo's settings over its algorithm's preset (:func:`~imssr.presets.build.demo_config`)."""


def markdown_table(rows: Sequence[Setting]) -> list[str]:
    """``rows`` as the lines of a Markdown table: field, value, source, note."""
    return ["| field | value | source | note |", "| --- | --- | --- | --- |",
            *(f"| `{r.field}` | `{show_value(r.value)}` | {r.source} | {r.note} |" for r in rows)]


def show_value(value) -> str:
    """A setting's value as the tables show it: JSON's words, thousands separated, ``""``."""
    if isinstance(value, bool):
        return str(value).lower()
    if isinstance(value, str):
        return value or '""'
    return f"{value:,}" if isinstance(value, int) else repr(value)
