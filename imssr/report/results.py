"""Reading a sweep directory back: every run's identity, budget (in agent steps) and evaluations.

Runs are found by their ``config.json`` at any depth below the root, so a report also works on hand-assembled
directories and on running sweeps; the sweep's own files add the runs planned but not started (``sweep.json``) and
those that failed every attempt (``sweep_status.json``).
"""
from __future__ import annotations

import functools
import math
import os
from dataclasses import dataclass, field
from typing import Any, Optional

from imssr.config import MAX_INT, steps_for_frames
from imssr.errors import ImssrError
from imssr.files import atomic_write_csv, read_csv
from imssr.rundir import (CHECKPOINT_DIR, CONFIG_FILE, DIVERGED, FAILED, TB_DIR, VIDEOS_DIR, RunDir, parse_run_path)
from imssr.sweep.directory import PLAN_FILE, PlannedRun, SweepDir
from imssr.sweep.grid import Run, beta_label, group_label

EVALUATIONS_COLUMNS = ["algo", "task", "mode", "seed", "step", "frame", "return", "beta0", "precision"]


@dataclass
class RunResult:
    """One run directory as the report sees it: which run, and what it holds."""

    run: Run
    """Which run; its beta_0 only when the run is a point of a beta sweep (a ``beta0_<value>`` directory level)."""
    steps: int
    """The run's budget T in agent steps."""
    action_repeat: int
    """Environment frames per agent step."""
    precision: str = "fp32"
    """The run's numerics, ``agent.precision_label`` (``fp32``, ``bf16``, ``bf16-fp32q``): a bf16
    run is its own group, never a seed of the fp32 one."""
    evals: list[tuple[str, int, int, float]] = field(default_factory=list)
    """``(mode, step, frame, return_mean)`` of every evaluation, in file order."""
    settings: dict[str, Any] = field(default_factory=dict, repr=False)
    """The run's config, flattened (``section.field -> value``): what tells apart two runs that
    share algo, task, seed and precision."""
    variant: str = ""
    """The settings that set this run apart from another run of the same algo, task, seed and
    precision (``intrinsic.normalization=zscore``); empty when no other run shares them."""
    provenance: list[dict] = field(default_factory=list)
    """The run's ``provenance.json`` records (:mod:`imssr.provenance`); [] when it has none."""
    state: str = ""
    """How the run stands when read (:meth:`RunDir.outcome <imssr.rundir.RunDir.outcome>`):
    ``new``, ``running``, ``interrupted``, ``finished``, ``failed`` or ``diverged``."""
    error: str = ""
    """The error line of a run whose last training failed or diverged (``status.json``)."""

    @property
    def label(self) -> str:
        """What tables and plots call the run's group: the algo, plus beta_0 in a beta sweep, the
        precision when it is not the paper's fp32, and the settings that set it apart from runs
        of the same algo, task and seed (:attr:`variant`)."""
        label = group_label(self.run.algo, self.run.beta0, self.precision)
        return f"{label} [{self.variant}]" if self.variant else label


@dataclass
class SweepResults:
    """Everything under a root: runs with their evaluations, the plan, and what was odd."""

    root: str
    runs: list[RunResult]
    planned: list[PlannedRun]
    """The runs ``sweep.json`` lists (they may not exist yet)."""
    notes: list[str]
    failures: dict[str, str] = field(default_factory=dict)
    """Run directory (absolute) -> last error, for every run that failed: listed as failed in
    ``sweep_status.json``, or whose own last training failed or diverged (``status.json``)."""
    skipped: dict[str, str] = field(default_factory=dict)
    """Run directory (absolute) -> why it is left out (an unreadable ``config.json`` or ``eval.csv``)."""
    def failure(self, run: Run) -> Optional[str]:
        """The last error of ``run`` when it failed (:attr:`failures`); None otherwise."""
        return self.failures.get(os.path.abspath(run.dir))

    @property
    def is_beta_sweep(self) -> bool:
        return any(r.run.beta0 is not None for r in self.runs) or any(p.run.beta0 is not None for p in self.planned)

    def budget(self, task: str) -> int:
        """The sweep's T for ``task`` in agent steps: the planned budget, else the largest budget of its runs."""
        return self._per_task[task][0]

    def action_repeat(self, task: str) -> Optional[int]:
        """The action repeat of ``task``'s runs; None when they differ (then a point in agent
        steps is no single frame count)."""
        return self._per_task[task][1]

    @functools.cached_property
    def _per_task(self) -> dict[str, tuple[int, Optional[int]]]:
        """Task -> ``(budget, action repeat)``, from one pass over the plan and the runs (complete
        once :func:`collect` returns): tables ask per row and point."""
        planned: dict[str, int] = {}
        for p in self.planned:
            planned[p.run.task] = max(p.steps, planned.get(p.run.task, p.steps))
        ran: dict[str, int] = {}
        repeats: dict[str, set[int]] = {}
        for r in self.runs:
            ran[r.run.task] = max(r.steps, ran.get(r.run.task, r.steps))
            repeats.setdefault(r.run.task, set()).add(r.action_repeat)
        return {task: (planned.get(task, ran.get(task)),
                       next(iter(repeats[task])) if len(repeats.get(task, ())) == 1 else None)
                for task in {*planned, *ran}}

    def frames_at(self, task: str, step: int) -> Optional[int]:
        """Agent step ``step`` of ``task`` in environment frames (None: mixed action repeats)."""
        repeat = self.action_repeat(task)
        return None if repeat is None else step * repeat


def collect(root: str) -> SweepResults:
    if not os.path.isdir(root):
        raise ImssrError(f"sweep directory not found: {root}")
    root = os.path.abspath(root)
    notes: list[str] = []
    runs = []
    skipped: dict[str, str] = {}
    for dirpath, dirnames, filenames in os.walk(root):
        dirnames[:] = sorted(d for d in dirnames if d not in (CHECKPOINT_DIR, TB_DIR, VIDEOS_DIR))
        run = _read_run(dirpath, root, notes, skipped) if CONFIG_FILE in filenames else None
        if run is not None:
            runs.append(run)
    if not runs:
        # Say which runs were found and why none can be read, not that there are none.
        why = [f"{os.path.relpath(d, root)}: {reason}" for d, reason in skipped.items()]
        raise ImssrError(f"no readable runs under {root}: " + "; ".join(why[:3])
                         + (f"; and {len(why) - 3} more" if len(why) > 3 else "") if why else
                         f"no runs under {root} (a run directory holds config.json and eval.csv)")
    set_apart(runs, root)
    try:
        planned = SweepDir(root).read_plan()
    except (OSError, ImssrError) as exc:
        notes.append(f"{PLAN_FILE}: unreadable ({exc}); expected seeds come from the runs found")
        planned = []
    failures = SweepDir(root).failed_runs()
    for result in runs:
        if result.state in (FAILED, DIVERGED):
            failures.setdefault(os.path.abspath(result.run.dir), result.error)
    results = SweepResults(root, runs, planned, notes, failures, skipped)
    found = {os.path.abspath(r.run.dir) for r in runs}
    for p in planned:
        if p.run.dir not in found and results.failure(p.run) is None:
            notes.append(f"{os.path.relpath(p.run.dir, root)}: planned but not started (no config.json)")
    return results


IDENTITY = ("algo", "env.task", "train.seed")
"""Settings that every run of a group may differ in (its seed) or that name the group already."""
RUN_ONLY = ("train.device", "train.torch_threads", "train.progress", "train.wandb", "train.wandb_group",
            "train.tensorboard", "train.replay_device", "train.gpu_share", "train.env_workers",
            "train.checkpoint_every_steps", "train.save_buffer", "train.keep_checkpoints")
"""Settings that say where and how a run was executed and what of it was kept, not what it
learned with: never a variant (checkpoints change no number: tests/test_checkpoint.py)."""


def set_apart(runs: list[RunResult], root: str) -> None:
    """Give runs that share algo, task, seed and precision but differ in other settings (two sweeps
    over one root that differ in a ``--set``) their :attr:`RunResult.variant`, the values of the
    settings in which they differ, so that a report never averages them as one group's seeds."""
    groups: dict[tuple[str, str], list[RunResult]] = {}
    for result in runs:
        groups.setdefault((result.run.task, result.label), []).append(result)
    for group in groups.values():
        seeds = [r.run.seed for r in group]
        if len(seeds) == len(set(seeds)):
            continue
        # Each setting's values over the group, so that thousands of runs of one seed cost linear
        # work, not a comparison of every run with every other.
        named = {k for result in group for k in result.settings} - {*IDENTITY, *RUN_ONLY}
        keys = sorted(k for k in named if len({repr(result.settings.get(k)) for result in group}) > 1)
        for result in group:
            # Runs alike in every setting (a copy of a run, the same sweep twice): their directories.
            result.variant = ", ".join(f"{k}={result.settings.get(k)}" for k in keys) or \
                os.path.relpath(os.path.dirname(result.run.dir), root)


def _read_run(run_dir: str, root: str, notes: list[str], skipped: dict[str, str]) -> Optional[RunResult]:
    """The run in ``run_dir``; None when it cannot be read, with why in ``skipped`` and ``notes``."""
    rel = os.path.relpath(run_dir, root)
    run_files = RunDir(run_dir)
    try:
        cfg = run_files.read_config()
        where = parse_run_path(rel)
        beta0 = float(cfg.intrinsic.beta0) if where is not None and where.beta0_label is not None else None
    except (ImssrError, OSError, ValueError, KeyError, TypeError) as exc:
        skipped[run_dir] = f"unreadable config.json ({exc})"
        notes.append(f"{rel}: {skipped[run_dir]}; skipped")
        return None
    repeat = cfg.env.action_repeat
    result = RunResult(Run(cfg.algo, cfg.env.task, cfg.train.seed, beta0, run_dir), cfg.train.steps, repeat,
                       precision=cfg.agent.precision_label, settings=cfg.flat())
    result.state, result.error = run_files.outcome()
    records = run_files.read_provenance()
    if records is None:
        notes.append(f"{rel}: unreadable provenance.json; its code and device are not known")
    result.provenance = records or []
    try:
        rows = read_csv(run_files.eval_log, complete_only=True)
    except ImssrError as exc:  # one damaged run must not stop a report of the others
        skipped[run_dir] = str(exc)
        notes.append(f"{rel}: {exc}; skipped")
        return None
    non_finite: list[str] = []
    not_counts: list[str] = []
    for row in rows:
        try:
            frame = _count(row["frame"], MAX_INT * MAX_INT)
            # Every eval.csv has a step column; a hand-made one without it gets the step at which
            # the loop reaches that frame.
            has_step = row.get("step") not in (None, "")
            step = _count(row["step"], MAX_INT) if has_step else \
                None if frame is None else steps_for_frames(frame, repeat)
            value = float(row["return_mean"])
        except (KeyError, TypeError, ValueError):
            continue  # a row cut short by a killed process
        if step is None or frame is None:
            # inf, 1e30 or -5 is no agent step: such a point would break every table and plot.
            not_counts.append(f"step {row['step']}, frame {row['frame']}" if has_step else f"frame {row['frame']}")
            continue
        if not math.isfinite(value):
            # A mean over seeds with a nan or inf in it says nothing: the point is left out, and said.
            non_finite.append(f"{value} at agent step {step:,} ({row['mode']})")
            continue
        result.evals.append((row["mode"], step, frame, value))
    for left_out, why, sep in ((non_finite, "with a non-finite return", ", "),
                               (not_counts, "with a step or frame that is no whole number of agent steps or frames",
                                "; ")):
        if left_out:
            notes.append(f"{rel}: {len(left_out)} evaluation(s) {why} left out: "
                         f"{sep.join(left_out[:3])}{sep + '...' if len(left_out) > 3 else ''}")
    if not result.evals:
        notes.append(f"{rel}: no evaluations yet")
    return result


def _count(text: str, most: int) -> Optional[int]:
    """``text`` as a count of agent steps or frames, an integer in ``[0, most]``; None for any
    other number (``inf``, ``1e30``, ``-5``, ``2.5``); ValueError when it is no number at all."""
    number = float(text)
    return int(number) if math.isfinite(number) and number.is_integer() and 0 <= number <= most else None


def write_evaluations(results: SweepResults, path: str) -> str:
    """Every evaluation of every run: ``algo,task,mode,seed,step,frame,return,beta0,precision``."""
    rows = sorted((r.run.algo, r.run.task, mode, r.run.seed, step, frame, ret,
                   "" if r.run.beta0 is None else beta_label(r.run.beta0), r.precision)
                  for r in results.runs for mode, step, frame, ret in r.evals)
    return atomic_write_csv(path, EVALUATIONS_COLUMNS,
                            ([algo, task, mode, seed, step, frame, f"{ret:.6g}", beta, precision]
                             for algo, task, mode, seed, step, frame, ret, beta, precision in rows))
