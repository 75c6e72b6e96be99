"""A run's config: a preset (:mod:`imssr.presets.tables`), a partial file or a saved run's
config, then the flags and ``section.field=value`` overrides of ``imssr train`` and every sweep run."""
from __future__ import annotations

from typing import Any, Mapping, Sequence

from imssr.config import RunConfig, apply_overrides, check_version, read_config_file, set_field, steps_for_frames
from imssr.errors import ImssrError
from imssr.presets.tables import DEMO, preset_settings


def make_config(algo: str, task: str, network: str = "dmcgb") -> RunConfig:
    """The configuration the authors ran for ``algo`` on ``task`` (Table III and Table V winning
    where they speak; :func:`preset_settings` gives every value's source)."""
    cfg = RunConfig()
    for row in preset_settings(algo, task, network):
        set_field(cfg, row.field, row.value)
    return cfg


def load_partial_config(path: str, algo: str | None = None, task: str | None = None,
                        network: str = "dmcgb") -> RunConfig:
    """A config file merged onto the preset of its algo and task (``imssr train --config``):
    every field the file gives wins, every other is the preset's, so a complete file (a run's
    ``config.json``) reads back as written.  The file's ``algo`` and ``env.task`` win over
    ``algo`` and ``task``; a config that names neither is an error."""
    data = read_config_file(path)
    if not isinstance(data, dict):
        raise ImssrError(f"a config must be a JSON object, got {type(data).__name__}")
    check_version(data, f"config {path}")
    file_algo = data.get("algo")
    file_task = data["env"].get("task") if isinstance(data.get("env"), dict) else None
    # A value of the wrong type is left for the type checks to name.
    algo = file_algo if isinstance(file_algo, str) else algo
    task = file_task if isinstance(file_task, str) else task
    # A preset is chosen only by name: a file that names none would otherwise train a default.
    missing = [name for name, value in (("algo", algo), ("env.task", task)) if value is None]
    if missing:
        raise ImssrError(f"config {path} names no {' and '.join(missing)}; add it to the file or pass "
                         f"{' and '.join('--' + name.split('.')[-1] for name in missing)}")
    merged = make_config(algo, task, network).to_dict()
    for key, value in data.items():
        if isinstance(value, dict) and isinstance(merged.get(key), dict):
            merged[key].update(value)
        else:
            merged[key] = value
    return RunConfig.from_dict(merged)


def run_config(algo: str | None = None, task: str | None = None, *, network: str | None = None,
               config_file: str | None = None, base: RunConfig | None = None, demo: bool = False,
               values: Mapping[str, Any] | None = None, frames: int | None = None, batch_size: int | None = None,
               beta0: float | None = None, overrides: Sequence[str] = ()) -> RunConfig:
    """The validated config of one run, as ``imssr train`` and every sweep run build it:
    :func:`base_config`'s, then ``values`` (``section.field`` -> value), ``frames`` (the budget in
    frames, rounded up to agent steps), ``batch_size`` (the RL batch, and the auxiliary batch of a
    task that trains on it), ``beta0`` and the ``overrides`` (``--set``), in that order."""
    cfg = base_config(algo, task, network=network, config_file=config_file, base=base, demo=demo)
    values = dict(values or {})
    if frames is not None:
        if values.get("train.steps") is not None:
            raise ImssrError("give the budget as --steps (agent steps) or --frames, not both")
        cfg.train.steps = steps_for_frames(frames, cfg.env.action_repeat)
    for dotted, value in values.items():
        set_field(cfg, dotted, value)
    if batch_size is not None:
        cfg.agent.batch_size = batch_size
        if not cfg.aux.own_batch:
            cfg.aux.batch_size = batch_size  # the task trains on the RL batch
    if beta0 is not None:
        if not cfg.intrinsic.enabled:
            raise ImssrError(f"--beta0 applies to algorithms with an intrinsic reward, not {cfg.algo}")
        cfg.intrinsic.beta0 = beta0
    return apply_overrides(cfg, list(overrides)).validate()


def base_config(algo: str | None = None, task: str | None = None, *, network: str | None = None,
                config_file: str | None = None, base: RunConfig | None = None, demo: bool = False) -> RunConfig:
    """What a run's settings start from, in this order: the file ``config_file`` (a partial one merged onto the
    preset of its algo and task, :func:`load_partial_config`), ``base`` (a resumed run's saved config,
    :func:`imssr.training.entry.resume_config`), or the preset of ``algo`` on ``task`` (the demo's with ``demo``).
    A given ``algo`` or ``task`` must agree with a loaded file or ``base``."""
    if config_file:
        cfg = load_partial_config(config_file, algo, task)
    elif base is not None:
        cfg = RunConfig.from_dict(base.to_dict())  # a copy: the settings below go on top
    else:
        algo = algo or ("im-curl" if demo else None)
        task = task or ("cartpole_swingup" if demo else None)
        if algo is None or task is None:
            raise ImssrError("train needs --algo and --task (see imssr algos, imssr tasks)")
        return (demo_config if demo else make_config)(algo, task, network or "dmcgb")
    if algo and algo != cfg.algo:
        raise ImssrError(f"--algo {algo} differs from the run's algo {cfg.algo}")
    if task and task != cfg.env.task:
        raise ImssrError(f"--task {task} differs from the run's task {cfg.env.task}")
    if network:
        raise ImssrError("--network chooses the preset of a new run; with --resume or --config "
                         "set agent.final_relu / feature_dim / projection_tanh instead")
    return cfg


def demo_config(algo: str = "im-curl", task: str = "cartpole_swingup", network: str = "dmcgb") -> RunConfig:
    """README command 1: a short IM-SSR run whose learning curve rises on 2 CPU cores, its settings
    (:data:`~imssr.presets.tables.DEMO`) chosen by measurement (docs/performance.md, "The demo").  Past about 1,000
    updates a young policy's evaluations swing, so the demo stops there.  A demonstration, not a result."""
    cfg = make_config(algo, task, network)
    for row in DEMO:
        set_field(cfg, row.field, row.value)
    if not cfg.aux.own_batch:
        cfg.aux.batch_size = cfg.agent.batch_size  # the task trains on the RL batch
    return cfg
