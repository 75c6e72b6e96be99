"""The paper's settings, each with its source: the rows every preset is made of.

The authors' code (``duchenzhuang/dmc-disentangle``, a fork of DMC-GB that produced the paper's numbers) where the
paper's tables are silent, Table III and Table V where they speak.  The rows of each base and signal are its
plug-in's (its ``*_spec.py``); those every algorithm shares are here.  :func:`preset_settings` gathers one preset's
(``imssr config --explain``).
"""
from __future__ import annotations

from typing import Sequence

from imssr.algos import AlgoSpec, get_algo
from imssr.auxiliary.registry import AUX_PLUGINS
from imssr.config import RunConfig
from imssr.envs.tasks import get_task
from imssr.errors import ImssrError
from imssr.intrinsic.registry import SIGNAL_PLUGINS
from imssr.settings import (AUTHORS, AUTHORS_LOOP, AUTHORS_SIGNAL, DMCGB, IMSSR, OFFICIAL_CURL, PAPER, TABLE3,
                            TABLE5, Setting)

# beta_0 for tasks outside Table V: the paper's most common small value.
DEFAULT_BETA0 = 0.01
# The paper's text keeps beta fixed on this task and decays it (x0.8 / 100k steps) elsewhere;
# the authors' IM-CURL script decays it there too (CURL's plug-in says so).
CONSTANT_BETA_TASKS = ("cartpole_swingup_sparse",)

# Each base's rows are its plug-in's (its auxiliary task's ``*_spec.py``), gathered here by base.
PAPER_BETA0 = {b: dict(p.beta0.by_task) for b, p in AUX_PLUGINS.items() if p.beta0.by_task}
"""Table V: beta_0 per base and task (../shared/spec/paper_beta0.csv; tests check the copy)."""


RUN = "run setting"
RUN_FIELDS = ("env.footage_dir", *(f for p in (*AUX_PLUGINS.values(), *SIGNAL_PLUGINS.values()) for f in p.run_fields),
              "train.save_buffer", "train.keep_checkpoints", "train.device", "train.replay_device", "train.gpu_share",
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
    Setting("agent.cuda_graphs", False, AUTHORS_LOOP, "kernels launched one by one from Python"),
    Setting("agent.batch_layout", "auto", IMSSR, "seeds side by side only: each member's update is "
            "its run's alone"),
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
and its action repeat, before the base's own (its plug-in's ``preset``)."""

INTRINSIC = (
    Setting("intrinsic.decay", 0.8, PAPER, "the authors' in_decay"),
    Setting("intrinsic.decay_every_steps", 100_000, PAPER, "agent steps (the authors' update step)"),
    Setting("intrinsic.normalization", "zscore", AUTHORS_SIGNAL),
    Setting("intrinsic.unbiased_std", True, AUTHORS_SIGNAL, "torch's default std"),
)
"""Settings every intrinsic reward shares, after its signal, beta_0 and its base's schedule (then
its base's normalisation epsilon, then :data:`INTRINSIC_LAST`)."""

INTRINSIC_LAST = (
    Setting("intrinsic.norm_rtol", 1e-5, IMSSR, "a batch of equal losses gets a zero bonus, not "
            "its rounding error divided by a tiny std"),
    Setting("intrinsic.form", "authors", AUTHORS_SIGNAL, "IM-CURL, IM-SODA: as the authors "
            "computed the signal (docs/algorithms.md); 'training' keeps the training loss's form"),
)
"""Settings every intrinsic reward shares, after its base's normalisation epsilon and before
its signal's own (its plug-in's ``preset``)."""


def _beta0(spec: AlgoSpec, task: str) -> Setting:
    """beta_0 of ``spec`` on ``task`` with its source: its base's Table V value (IM-CURL, IM-SODA), else the paper's
    one value for the base (IM-PAD, IM-SVEA: 0.05), else :data:`DEFAULT_BETA0`; RND and RE3 take the IM- variant's, so
    that a comparison changes only the signal."""
    beta0 = AUX_PLUGINS[spec.base].beta0
    if task in beta0.by_task:
        value, source = beta0.by_task[task], TABLE5
    elif beta0.every_task is not None:
        value, source = beta0.every_task, beta0.every_task_source
    else:
        return Setting("intrinsic.beta0", DEFAULT_BETA0, IMSSR, f"no value in the paper for {task}: {DEFAULT_BETA0}")
    note = "the IM- variant's value, so that only the signal changes" if spec.intrinsic != "ssl" else \
        beta0.notes.get(task, "")
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
    """Every value the preset of ``algo`` on ``task`` sets, with its source, in order; a later
    setting of the same field wins."""
    spec = get_algo(algo)
    tspec = get_task(task)
    base = AUX_PLUGINS[spec.base]
    if network not in NETWORKS:
        raise ImssrError(f"unknown network {network!r}; valid: {', '.join(NETWORKS)}")
    rows = [Setting("algo", spec.name, "user"), Setting("env.task", tspec.name, "user"),
            Setting("env.action_repeat", tspec.action_repeat, TABLE3), *COMMON,
            Setting("aux.name", spec.aux, "algo"), *base.preset]
    if spec.intrinsic_enabled:
        schedule = base.constant_beta_schedule if tspec.name in CONSTANT_BETA_TASKS else base.schedule
        rows += [Setting("intrinsic.enabled", True, "algo"), Setting("intrinsic.source", spec.intrinsic, "algo"),
                 _beta0(spec, tspec.name), schedule, *INTRINSIC, base.norm_eps, *INTRINSIC_LAST,
                 *SIGNAL_PLUGINS[spec.intrinsic].preset]
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
