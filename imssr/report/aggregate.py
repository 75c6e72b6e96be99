"""Aggregate metrics across tasks with rliable (Agarwal et al. 2021).

Scores are returns divided by 1000, the maximum episode return of every DMC task, so tasks weigh alike.  Per mode and
fraction of T: each algo's interquartile mean (IQM) with a 95% stratified-bootstrap interval.  Comparisons of two
algorithms are made within a task (:mod:`imssr.report.comparisons`), not pooled here.
"""
from __future__ import annotations

import warnings
from dataclasses import dataclass
from typing import Optional

import numpy as np

from imssr.errors import ImssrError
from imssr.extras import require
from imssr.files import atomic_write_csv
from imssr.report.stats import MIN_SEEDS_FOR_BOOTSTRAP
from imssr.report.tables import FRACTIONS, Row, mode_order

DMC_MAX_RETURN = 1000.0
AGGREGATE_COLUMNS = ["mode", "fraction", "metric", "label", "point", "ci_low", "ci_high", "tasks", "runs"]


@dataclass
class Aggregate:
    """One metric of one algo (or pair of algos) at one mode and fraction of T."""

    mode: str
    fraction: float
    metric: str
    """``IQM``."""
    label: str
    """The algo (with its beta_0 and precision, as the table's rows)."""
    point: float
    ci_low: float
    ci_high: float
    tasks: list[str]
    """Tasks the metric averages over (those where every compared algo has a score)."""
    runs: int
    """Runs per task used (the fewest any of the tasks has: rliable needs a full matrix)."""


def score_matrix(rows: list[Row], fraction_index: int, tasks: list[str]) -> np.ndarray:
    """``(runs, tasks)`` normalised scores of one label's rows; runs = the fewest seeds of any task
    (each task's seeds in seed order, truncated), so the matrix has no holes."""
    per_task = {row.task: row.cells[fraction_index].values for row in rows}
    n = min(len(per_task[t]) for t in tasks)
    cols = [[per_task[t][s] for s in sorted(per_task[t])[:n]] for t in tasks]
    return np.array(cols, dtype=float).T / DMC_MAX_RETURN


def compute(rows: list[Row], reps: int = 2000, seed: int = 0) -> tuple[list[Aggregate], list[str]]:
    """IQM per label where every task it averages has at least
    :data:`~imssr.report.stats.MIN_SEEDS_FOR_BOOTSTRAP` seeds (with fewer, the IQM is about the
    mean and the interval about [min, max]); without rliable none, and a note (also printed as a warning)."""
    out: list[Aggregate] = []
    notes: list[str] = []
    missing: Optional[str] = None
    for mode in mode_order(r.mode for r in rows):
        by_label: dict[str, list[Row]] = {}
        for row in rows:
            if row.mode == mode:
                by_label.setdefault(row.label, []).append(row)
        for i, fraction in enumerate(FRACTIONS):
            scored = {label: {r.task for r in group if r.cells[i].n} for label, group in by_label.items()}
            scored = {label: tasks for label, tasks in scored.items() if tasks}
            if not scored:
                continue
            common = sorted(set.intersection(*scored.values()))
            if not common:
                notes.append(f"{mode} at {fraction:.1f}T: no task has a score for every algo; no IQM")
                continue
            dropped = sorted(set.union(*scored.values()) - set(common))
            if dropped:
                notes.append(f"{mode} at {fraction:.1f}T: IQM over {', '.join(common)} only "
                             f"(not every algo has {', '.join(dropped)})")
            matrices = {label: score_matrix(by_label[label], i, common) for label in scored}
            few = {label: m.shape[0] for label, m in matrices.items() if m.shape[0] < MIN_SEEDS_FOR_BOOTSTRAP}
            if few:
                notes.append(f"{mode} at {fraction:.1f}T: no IQM or bootstrap interval: "
                             + ", ".join(f"{label} has {n} seed{'s' if n > 1 else ''}" for label, n in few.items())
                             + f" on some task, and they need at least {MIN_SEEDS_FOR_BOOTSTRAP} (with fewer, the "
                             "IQM is about the mean and the interval about [min, max])")
                matrices = {label: m for label, m in matrices.items() if label not in few}
            if not matrices:
                continue
            try:
                point, ci = _iqm_estimates(matrices, reps, seed)
            except ImssrError as exc:  # rliable is not installed
                missing = f"no IQM: {exc}"
                continue
            for label, m in matrices.items():
                out.append(Aggregate(mode, fraction, "IQM", label, float(point[label][0]),
                                     float(ci[label][0][0]), float(ci[label][1][0]), common, m.shape[0]))
    if missing:
        notes.append(missing)
        print(f"imssr: warning: {missing}", flush=True)
    return out, notes


def _iqm_estimates(scores: dict, reps: int, seed: int):
    """rliable's IQM with its stratified-bootstrap interval, with a fixed seed (a report is reproducible)."""
    rly = require("rliable.library", "report")
    metrics = require("rliable.metrics", "report")

    def iqm(x: np.ndarray) -> np.ndarray:
        return np.array([metrics.aggregate_iqm(x)])

    # rliable 1.2 draws its resamples with numpy's global generator (np.random.choice), whatever
    # random_state it is given: seed that generator for the call and give the caller's back after.
    outside = np.random.get_state()
    np.random.seed(seed)
    try:
        with warnings.catch_warnings():
            # rliable 1.2 passes a RandomState through arch's deprecated `random_state` keyword.
            warnings.filterwarnings("ignore", message="random_state is deprecated", category=FutureWarning)
            return rly.get_interval_estimates(scores, iqm, reps=reps, random_state=np.random.RandomState(seed))
    finally:
        np.random.set_state(outside)


def markdown(aggregates: list[Aggregate]) -> str:
    if not aggregates:
        return (f"No aggregate metrics: each needs a score on every task it averages and at least "
                f"{MIN_SEEDS_FOR_BOOTSTRAP} seeds per task (the Notes say which are missing).\n")
    lines = ["| mode | T | metric | algo | estimate | 95% CI | tasks | runs/task |",
             "|---|---:|---|---|---:|---|---|---:|"]
    for a in aggregates:
        lines.append(f"| `{a.mode}` | {a.fraction:.1f}T | {a.metric} | {a.label} | {a.point:.3f} | "
                     f"[{a.ci_low:.3f}, {a.ci_high:.3f}] | {', '.join(a.tasks)} | {a.runs} |")
    return "\n".join(lines) + "\n"


def write_csv(aggregates: list[Aggregate], path: str) -> str:
    return atomic_write_csv(path, AGGREGATE_COLUMNS, (
        [a.mode, f"{a.fraction:.1f}", a.metric, a.label, f"{a.point:.6g}",
         f"{a.ci_low:.6g}", f"{a.ci_high:.6g}", ";".join(a.tasks), a.runs] for a in aggregates))
