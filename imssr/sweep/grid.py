"""Sweep grids: what to run (algos x tasks x seeds [x beta_0]) and where each run lives.

:class:`SweepConfig` is a sweep's settings, one typed field each, whose docstrings are the CLI's help.  :class:`Run`
names one run of a grid, whose directory is a pure function of its grid point
(``ROOT/<task>/<algo>/[beta0_<value>/]seed_<n>``), so re-running a sweep finds its runs again.
"""
from __future__ import annotations

import functools
import math
import os
import re
import typing
from dataclasses import dataclass, field, fields
from typing import Any, Optional

from imssr.config import MAX_SEED, SEED_RULE, RunConfig, dataclass_field_types, logger_fields, type_phrase
from imssr.envs import get_task
from imssr.errors import ImssrError
from imssr.jsonio import read_json
from imssr.presets import ALGOS, get_algo
from imssr.rundir import RunDir, run_path

LAUNCHERS = ("ray", "slurm", "local")
"""What ``imssr sweep --launcher`` takes (:mod:`imssr.sweep.launchers`)."""


@dataclass
class SweepConfig:
    """One sweep: the grid and how its runs are dispatched.  Each field is a key of a sweep file and
    a flag of ``imssr sweep`` (:func:`setting_key`), whose help is the field's docstring."""

    root: str = "runs/sweep"
    """Directory of the sweep: every run of it, ``sweep.json`` and ``sweep_status.json``; in a
    sweep file a leading ``~`` is the home directory, as on the command line."""
    algos: list[str] = field(default_factory=list)
    """Algorithms, see ``imssr algos``: ``a,b``, or a list in a sweep file."""
    tasks: list[str] = field(default_factory=list)
    """Tasks, see ``imssr tasks``: ``t1,t2``, or a list in a sweep file."""
    seeds: list[int] = field(default_factory=lambda: [1])
    """Seeds, one run each per algo and task: a list, a range or both (``1,2,3``, ``1-5``, ``1-3,7``)."""
    steps: Optional[int] = None
    """Budget T of every run in agent steps (the report's T); none (and no ``frames``): the preset's, 500,000."""
    frames: Optional[int] = None
    """Alternative to ``steps``: the budget in environment frames, passed on as ``imssr train
    --frames`` so that each run trains ``frames / action_repeat`` agent steps of its own task,
    rounded up.  At most one of ``steps`` and ``frames``."""
    overrides: list[str] = field(default_factory=list)
    """``section.field=value`` overrides applied to every run, as ``imssr train --set`` takes them
    (``set`` in a sweep file; the flag is repeatable and adds to the file's)."""
    beta0: list[float] = field(default_factory=list)
    """beta_0 values of a beta sensitivity sweep, e.g. ``0.001,0.01,0.05,0.1`` (one run per value
    for algos with an intrinsic reward; base algos run once as the beta_0 = 0 reference); empty:
    each preset's beta_0."""
    retries: int = 1
    """Extra attempts of a failed run (each resumes from the run's checkpoint if it has one)."""
    cpus_per_run: float = 1.0
    """CPUs per run: what Ray reserves for it and what the local launcher counts; also the run's
    torch/OpenMP threads (``train.torch_threads``, at least 1, unless the overrides set it)."""
    gpus_per_run: float = 0.0
    """GPUs (fractions allowed) Ray reserves per run; > 0 trains on ``cuda`` unless ``train.device`` is overridden."""
    max_parallel: int = 0
    """Runs in flight at once; 0: as many as the cluster's CPUs and GPUs hold."""
    address: str = ""
    """Address of an existing Ray cluster, e.g. ``10.0.0.1:6379`` (``ray start --head`` prints it);
    empty: a local Ray started for this sweep and shut down after it."""
    launcher: str = "ray"
    """How runs are dispatched: ``ray`` (a local Ray or the cluster at ``address``), ``slurm`` (one SLURM job per
    run through submitit, the ``slurm`` extra) or ``local`` (subprocesses of the sweep itself, no Ray)."""
    slurm_partition: str = ""
    """SLURM partition of the jobs (``--launcher slurm``); empty: the cluster's default."""
    slurm_time: int = 0
    """Time limit of each SLURM job in minutes; 0: 24 hours.  A run cut by the limit is retried
    from its last checkpoint."""
    slurm_gpus_per_task: int = 0
    """GPUs of each SLURM job; > 0 trains on ``cuda`` unless ``train.device`` is overridden."""
    slurm_array_parallelism: int = 0
    """SLURM jobs of the sweep's job array running at once; 0: as many as SLURM allows (256)."""
    runs_per_process: int = 1
    """Runs trained in one process as one batch of agents, at most this many (``imssr train --runs``: each the run
    it would be alone); runs that differ only in the seed and in the intrinsic reward's beta_0 or on/off can share a
    process (a grid point's seeds, a base algo and its IM- variant, a beta_0 sweep).  1: one run per process, faster
    than every stacked layout measured on the CPU and on CUDA (docs/performance.md); 0: all that can share.  A
    process takes the CPUs and GPUs of one run."""
    logger: str = ""
    """Every run's ``imssr train --logger`` (e.g. ``csv,tensorboard,wandb``); empty: train's default.  With
    ``wandb``, runs are grouped under the root's name in W&B and tagged with their algo, task, seed and beta_0."""

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> "SweepConfig":
        """A sweep from a JSON object whose keys are the CLI's (:func:`setting_key`: ``set`` for
        overrides; ``-`` or ``_``); a leading ``~`` of its root is the home directory."""
        if not isinstance(data, dict):
            raise ImssrError(f"a sweep file must hold a JSON object, got {type(data).__name__}")
        data = {k.replace("-", "_"): v for k, v in data.items()}
        if "set" in data:
            data["overrides"] = data.pop("set")
        names = [f.name for f in fields(cls)]
        unknown = sorted(set(data) - set(names))
        if unknown:
            raise ImssrError(f"unknown sweep setting(s): {', '.join(unknown)}; valid: "
                             f"{', '.join(sorted(setting_key(n) for n in names))}")
        cfg = cls()
        for name, value in data.items():
            setattr(cfg, name, _coerce(name, value))
        # A committed sweep file can keep its runs outside the repository ("~/imssr-runs/...").
        cfg.root = os.path.expanduser(cfg.root)
        return cfg

    def validate(self) -> "SweepConfig":
        checks = [
            (self.steps is None or self.frames is None,
             "give the budget as --steps (agent steps) or --frames, not both"),
            (bool(self.algos), "a sweep needs --algos (see imssr algos)"),
            (bool(self.tasks), "a sweep needs --tasks (see imssr tasks)"),
            (bool(self.seeds), "a sweep needs --seeds"),
            (bool(self.root.strip()), 'the sweep\'s root is empty: give --root DIR (or "root" in the sweep file)'),
            (self.steps is None or self.steps >= 1, "--steps must be >= 1"),
            (self.frames is None or self.frames >= 1, "--frames must be >= 1"),
            (self.retries >= 0, "--retries must be >= 0"),
            (0 < self.cpus_per_run < math.inf, "--cpus-per-run must be a finite number > 0"),
            (0 <= self.gpus_per_run < math.inf, "--gpus-per-run must be a finite number >= 0"),
            (self.max_parallel >= 0, "--max-parallel must be >= 0"),
            (self.runs_per_process >= 0, "--runs-per-process must be >= 0"),
            # The same rule as imssr train's (train.seed): a seed it refuses would fail every run.
            (all(0 <= s <= MAX_SEED for s in self.seeds),
             f"seeds must be {SEED_RULE}, got {next((s for s in self.seeds if not 0 <= s <= MAX_SEED), None)}"),
            (all(0 <= b < math.inf for b in self.beta0), "--beta0 values must be >= 0 and finite"),
            (self.launcher in LAUNCHERS, f"--launcher must be one of {', '.join(LAUNCHERS)}, got {self.launcher!r}"),
            (self.slurm_time >= 0, "--slurm-time must be >= 0 (minutes)"),
            (self.slurm_gpus_per_task >= 0, "--slurm-gpus-per-task must be >= 0"),
            (self.slurm_array_parallelism >= 0, "--slurm-array-parallelism must be >= 0"),
            (self.launcher == "slurm" or not (self.slurm_partition or self.slurm_time or self.slurm_gpus_per_task
                                              or self.slurm_array_parallelism),
             "the --slurm-* settings go with --launcher slurm"),
            (self.launcher == "ray" or not self.address, "--address (a Ray cluster) goes with --launcher ray"),
        ]
        for ok, message in checks:
            if not ok:
                raise ImssrError(message)
        for algo in self.algos:
            get_algo(algo)
        for task in self.tasks:
            get_task(task)
        # The run settings the grid gives each run, which an override would silently replace: field -> its setting.
        grid = {"algo": "--algos", "env.task": "--tasks", "train.seed": "--seeds"}
        if self.beta0:
            grid["intrinsic.beta0"] = "--beta0"
        if self.steps is not None or self.frames is not None:
            grid.update(dict.fromkeys(("train.steps", "train.frames"), "--steps/--frames"))
        for key in (override.partition("=")[0].strip() for override in self.overrides):
            if key in grid:
                raise ImssrError(f"--set {key} is set by the sweep's grid for every run ({grid[key]}); "
                                 "leave it out of --set")
        if self.logger:
            logger_fields(self.logger)
        if self.beta0 and not any(ALGOS[a].intrinsic_enabled for a in self.algos):
            raise ImssrError("--beta0 needs an algo with an intrinsic reward (im-X, X+rnd, X+re3)")
        return self


@dataclass(frozen=True)
class Run:
    """Which run: one grid point and its directory, a single ``imssr train`` run, for the sweep
    that trains it and for the report that reads it back."""

    algo: str
    """Algorithm name."""
    task: str
    """Task name."""
    seed: int
    """Run seed."""
    beta0: Optional[float]
    """beta_0 of a beta sweep; None: the preset's (and for base algos, and runs outside a beta sweep)."""
    dir: str
    """Run directory (absolute)."""

    @functools.cached_property
    def run_dir(self) -> RunDir:
        """The run directory's files and life."""
        return RunDir(self.dir)

    @property
    def name(self) -> str:
        """Short label for logs and the status file."""
        beta = "" if self.beta0 is None else f" beta0={beta_label(self.beta0)}"
        return f"{self.algo} {self.task}{beta} seed {self.seed}"

    def resolved_config(self, cfg: SweepConfig) -> RunConfig:
        """The run's whole config, which the sweep writes to its ``config.json``: the preset of its
        algo and task (a run with a checkpoint: its own ``config.json``), then the sweep's seed,
        budget, device, threads and loggers, then the overrides."""
        # Progress on: the training writes into its sweep.log, no terminal, so a line a minute, no bar.
        values: dict[str, Any] = {"train.seed": self.seed, "train.progress": True,
                                  "train.torch_threads": max(1, int(cfg.cpus_per_run))}
        if cfg.steps is not None:
            values["train.steps"] = cfg.steps
        gpus = cfg.slurm_gpus_per_task if cfg.launcher == "slurm" else cfg.gpus_per_run  # from its launcher
        if gpus > 0 and not any(o.startswith("train.device=") for o in cfg.overrides):  # the override wins
            values["train.device"] = "cuda"
        if 0 < gpus < 1:
            # Runs share a GPU: each places its replay frames within its share of the memory.
            values["train.gpu_share"] = gpus
        if cfg.logger:
            values.update(logger_fields(cfg.logger))
            if values["train.wandb"]:  # grouped under the root directory's name
                values["train.wandb_group"] = os.path.basename(os.path.abspath(cfg.root))
        # Planned as `imssr train [--resume]` plans it (no torch: the trainer is not loaded).
        from imssr.training.entry import TrainRequest, plan

        resume = self.run_dir.has_checkpoint() and self.run_dir.has_config()
        request = TrainRequest(algo=self.algo, task=self.task, out=self.run_dir.path, resume=resume, values=values,
                               frames=cfg.frames if cfg.steps is None else None, beta0=self.beta0,
                               overrides=cfg.overrides)
        return plan(request)[0].config


def beta_label(value: float) -> str:
    """Directory-safe, round-tripping text of a beta_0 (0.001 -> '0.001', 1e-05 -> '1e-05')."""
    return repr(float(value))


def group_label(algo: str, beta0: Optional[float], precision: str = "fp32") -> str:
    """What reports call the group of a run: the algo, plus beta_0 for a point of a beta sweep, plus
    the precision unless fp32 (``"im-curl beta0=0.01 bf16"``)."""
    label = algo if beta0 is None else f"{algo} beta0={beta_label(beta0)}"
    return label if precision == "fp32" else f"{label} {precision}"


def expand(cfg: SweepConfig) -> list[Run]:
    """Every run of the grid, in a stable order (task, algo, beta_0, seed)."""
    root = os.path.abspath(cfg.root)
    runs = []
    for task in cfg.tasks:
        for algo in cfg.algos:
            # Base algos have no beta_0: in a beta sweep they run once, as the beta_0 = 0 line.
            betas = cfg.beta0 if (cfg.beta0 and ALGOS[algo].intrinsic_enabled) else [None]
            for beta in betas:
                label = None if beta is None else beta_label(beta)
                for seed in cfg.seeds:
                    runs.append(Run(algo, task, seed, beta, run_path(root, task, algo, seed, label)))
    return runs


# -- parsing -----------------------------------------------------------------------------
def parse_names(text: Any, what: str) -> list[str]:
    """``a,b`` or a JSON list -> names, without repeats."""
    items = text if isinstance(text, list) else str(text).split(",")
    names = [str(i).strip() for i in items if str(i).strip()]
    if not names:
        raise ImssrError(f"no {what} given")
    return list(dict.fromkeys(names))


MAX_SEEDS = 100_000
"""The most seeds one seed list may name (each is a run per algo and task)."""


def parse_seeds(text: Any, repeats: bool = True) -> list[int]:
    """``1,2,3``, ``1-5``, ``1-3,7`` or a JSON list of integers -> seeds, each once: a seed named
    twice is dropped (``repeats``) or refused in one line (``imssr train --seeds``)."""
    items = text if isinstance(text, list) else str(text).split(",")
    seeds: list[int] = []
    for item in items:
        part = str(item).strip()  # an integer of a JSON list too (true is "True": a bad seed)
        if not part:
            # 1,,2 or 1,2, is a seed left out or a typo: which one is not ours to guess.
            raise ImssrError(f"bad seeds {text!r}: an empty item between commas; "
                             "expected integers like 1,2,3 or a range like 1-5")
        # A leading minus is a negative seed (refused as such), not a range.
        match = _SEED_ITEM.match(part)
        if match is None:
            raise ImssrError(f"bad seeds {part!r}: expected integers like 1,2,3 or a range like 1-5")
        a = _seed(int(match[1]))
        b = a if match[2] is None else _seed(int(match[2]))  # a seed is the range a-a
        if a > b:
            raise ImssrError(f"bad seed range {part!r}: {a} > {b}")
        # Checked before the list is built: a typo like 5-3000000000 would fill memory.
        if b - a + 1 > MAX_SEEDS:
            raise ImssrError(f"bad seed range {part!r}: {b - a + 1:,} seeds, at most {MAX_SEEDS:,}")
        seeds.extend(range(a, b + 1))
    if not seeds:
        raise ImssrError("no seeds given")
    unique = list(dict.fromkeys(seeds))
    if not repeats and len(unique) < len(seeds):
        seen: set[int] = set()
        twice = next(s for s in seeds if s in seen or seen.add(s))
        raise ImssrError(f"seed {twice} is named twice in --seeds {text if isinstance(text, str) else seeds}: "
                         "each seed trains one run; name it once")
    return unique


_SEED_ITEM = re.compile(r"^(-?[0-9]+)(?:\s*-\s*(-?[0-9]+))?$")
"""One item of a seed list: a seed, or a range ``a-b`` (either end may carry a minus sign)."""


def _seed(value: int) -> int:
    """``value``, or a one-line error when it is negative (:data:`MAX_SEED` is checked later)."""
    if value < 0:
        raise ImssrError(f"seeds must be {SEED_RULE}, got {value}")
    return value


def parse_floats(text: Any, what: str) -> list[float]:
    items = text if isinstance(text, list) else str(text).split(",")
    values = []
    for item in items:
        if isinstance(item, str) and not item.strip():
            continue
        try:
            value = float(item)
        except (TypeError, ValueError):
            raise ImssrError(f"bad {what} value {item!r}: expected numbers like 0.001,0.01") from None
        if not 0 <= value < math.inf:  # also NaN
            raise ImssrError(f"{what} values must be >= 0 and finite, got {item!r}")
        values.append(value)
    if not values:
        raise ImssrError(f"no {what} values given")
    return list(dict.fromkeys(values))


def setting_key(name: str) -> str:
    """The key of the :class:`SweepConfig` field ``name`` in a sweep file, and its flag without the
    dashes: the field's name, except ``set`` for the overrides (as ``imssr train --set``)."""
    return "set" if name == "overrides" else name


def setting_type(name: str) -> tuple[Any, bool]:
    """The declared type of the :class:`SweepConfig` field ``name`` (``X`` of ``Optional[X]``), and
    whether None is one of its values."""
    kind = dataclass_field_types(SweepConfig)[name]
    if type(None) in typing.get_args(kind):
        return next(k for k in typing.get_args(kind) if k is not type(None)), True
    return kind, False


def _coerce(name: str, value: Any) -> Any:
    """A value of the :class:`SweepConfig` field ``name`` in the field's declared type: text of a
    list (``a,b``, seeds ``1-5``) is parsed, a value of the wrong type is a one-line error."""
    kind, optional = setting_type(name)
    if name == "overrides":
        if not isinstance(value, list) or not all(isinstance(v, str) for v in value):
            raise ImssrError('sweep file: "set" must be a list of "section.field=value" strings')
        return list(value)
    if optional and value is None:
        return None
    if typing.get_origin(kind) is list:
        item = typing.get_args(kind)[0]
        if item is int:
            return parse_seeds(value)
        return parse_floats(value, name) if item is float else parse_names(value, name)
    if kind is str:
        if not isinstance(value, str):
            raise ImssrError(f"sweep file: {name!r} must be a string")
        return value
    try:
        if isinstance(value, bool) or not isinstance(value, (int, float)) or \
                (kind is int and isinstance(value, float) and not value.is_integer()):
            raise ValueError
        return kind(value)
    except (ValueError, OverflowError):  # OverflowError: an integer too large for a float
        raise ImssrError(f"sweep file: {name!r} must be {type_phrase(kind)}, got {value!r}") from None


def load_sweep_file(path: str) -> SweepConfig:
    return SweepConfig.from_dict(read_json(path, "sweep file"))


def sweep_config(values: dict[str, Any], file: Optional[str] = None) -> SweepConfig:
    """The sweep ``imssr sweep`` describes, not yet validated: the sweep file's settings (no file:
    the defaults), then ``values`` over them, a field's name -> the value of its flag for each flag
    given.  ``overrides`` add to the file's, and a budget in either unit replaces the file's."""
    cfg = load_sweep_file(file) if file else SweepConfig()
    if "steps" in values or "frames" in values:
        cfg.steps = cfg.frames = None
    for name, value in values.items():
        value = _coerce(name, value)
        setattr(cfg, name, cfg.overrides + value if name == "overrides" else value)
    return cfg
