"""Aggregate metrics across tasks with rliable (Agarwal et al. 2021).

Scores are returns divided by 1000, the maximum episode return of every DMC task, so tasks
weigh alike.  Per mode and fraction of T: the interquartile mean (IQM) of each algo with a
95% stratified-bootstrap confidence interval, and the probability that each algo with an
intrinsic reward (IM-X, and X+RND / X+RE3) beats its base X on a randomly drawn task.
"""
from __future__ import annotations

import warnings
from dataclasses import dataclass
from typing import Optional

import numpy as np

from imssr.extras import require
from imssr.files import atomic_write_csv
from imssr.presets import ALGOS
from imssr.report.results import group_label
from imssr.report.tables import FRACTIONS, Row, mode_order

# The report extra; imported with this module, which only `imssr report` imports.
rly = require("rliable.library", "report")
metrics = require("rliable.metrics", "report")

DMC_MAX_RETURN = 1000.0
AGGREGATE_COLUMNS = ["mode", "fraction", "metric", "label", "point", "ci_low", "ci_high", "tasks", "runs"]


@dataclass
class Aggregate:
    """One metric of one algo (or pair of algos) at one mode and fraction of T."""

    mode: str
    fraction: float
    metric: str
    """``IQM`` or ``P(X > Y)``."""
    label: str
    """The algo, or ``X > Y`` for a probability of improvement."""
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
    """IQM per label and probability of improvement per (intrinsic label, base) pair."""
    out: list[Aggregate] = []
    notes: list[str] = []

    def iqm(x: np.ndarray) -> np.ndarray:
        return np.array([metrics.aggregate_iqm(x)])

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
            else:
                dropped = sorted(set.union(*scored.values()) - set(common))
                if dropped:
                    notes.append(f"{mode} at {fraction:.1f}T: IQM over {', '.join(common)} only "
                                 f"(not every algo has {', '.join(dropped)})")
                matrices = {label: score_matrix(by_label[label], i, common) for label in scored}
                point, ci = _estimates(matrices, iqm, reps, seed)
                for label, m in matrices.items():
                    out.append(Aggregate(mode, fraction, "IQM", label, float(point[label][0]),
                                         float(ci[label][0][0]), float(ci[label][1][0]), common, m.shape[0]))
            for label in scored:
                base = _base_label(label, by_label, ALGOS)
                if base is None or base not in scored:
                    continue
                tasks = sorted(scored[label] & scored[base])
                if not tasks:
                    continue
                x = score_matrix(by_label[label], i, tasks)
                y = score_matrix(by_label[base], i, tasks)
                key = f"{label} > {base}"
                point, ci = _estimates({key: (x, y)}, metrics.probability_of_improvement, reps, seed)
                low, high = np.ravel(ci[key])
                out.append(Aggregate(mode, fraction, "P(X > Y)", key, float(point[key]),
                                     float(low), float(high), tasks, min(x.shape[0], y.shape[0])))
    return out, notes


def _estimates(scores: dict, func, reps: int, seed: int):
    """rliable's bootstrap with a fixed seed, so a report is reproducible."""
    with warnings.catch_warnings():
        # rliable 1.2 passes a RandomState through arch's deprecated `random_state` keyword.
        warnings.filterwarnings("ignore", message="random_state is deprecated", category=FutureWarning)
        return rly.get_interval_estimates(scores, func, reps=reps, random_state=np.random.RandomState(seed))


def _base_label(label: str, by_label: dict, algos) -> Optional[str]:
    """The base algo's label, at the same precision, for a label whose algo has an intrinsic
    reward (else None)."""
    row = by_label[label][0]
    spec = algos.get(row.algo)
    if spec is None or not spec.intrinsic_enabled:
        return None
    return group_label(spec.base, None, row.precision)


def markdown(aggregates: list[Aggregate]) -> str:
    if not aggregates:
        return "No aggregate metrics (no task has scores for the compared algos).\n"
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
