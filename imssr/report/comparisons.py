"""Comparisons within one task, mode and fraction of T (never pooled, where seeds of different things would stand in
for each other): an algorithm with an intrinsic reward against its base at the same precision, and an algorithm at
another precision against itself at fp32.  Each gives n on both sides, the difference of means, P(X > Y) and the
two-sided Mann-Whitney p-value (two-sided: no direction was fixed before the runs).
"""
from __future__ import annotations

from dataclasses import dataclass

from imssr.files import atomic_write_csv
from imssr.presets import ALGOS
from imssr.report.stats import Comparison, compare
from imssr.report.tables import FRACTIONS, Row
from imssr.sweep.grid import group_label

COLUMNS = ["mode", "task", "fraction", "x", "y", "n_x", "n_y", "mean_x", "mean_y", "difference",
           "p_x_beats_y", "p_value", "exact"]


@dataclass(frozen=True)
class Pair:
    """Row ``x`` against row ``y`` at one fraction of T."""

    mode: str
    task: str
    fraction: float
    x: str
    y: str
    result: Comparison


def partner(row: Row) -> list[str]:
    """The labels ``row`` is compared against: its base (an intrinsic reward) and its fp32 self (another precision)."""
    out = []
    spec = ALGOS.get(row.algo)
    if spec is not None and spec.intrinsic_enabled:
        out.append(group_label(spec.base, None, row.precision))
    if row.precision != "fp32":
        out.append(group_label(row.algo, row.beta0, "fp32"))
    return out


def compute(rows: list[Row]) -> list[Pair]:
    by_key = {(r.mode, r.task, r.label): r for r in rows}
    pairs = []
    for row in rows:
        for other_label in partner(row):
            other = by_key.get((row.mode, row.task, other_label))
            if other is None:
                continue
            for i, fraction in enumerate(FRACTIONS):
                x, y = row.cells[i].values, other.cells[i].values
                if x and y:
                    pairs.append(Pair(row.mode, row.task, fraction, row.label, other.label,
                                      compare([x[s] for s in sorted(x)], [y[s] for s in sorted(y)])))
    return pairs


def markdown(pairs: list[Pair]) -> str:
    if not pairs:
        return "No pairs to compare (an algorithm with an intrinsic reward beside its base, or a precision " \
               "beside fp32, on the same task).\n"
    lines = ["Within one task, mode and point: P(X > Y) is the fraction of (x, y) seed pairs where X's run "
             "ends higher (ties half); p is the two-sided Mann-Whitney test of no difference, exact over "
             "every split of the pooled seeds (with 3 seeds against 3 the smallest possible p is 0.10).\n",
             "| mode | task | T | X | Y | n (X, Y) | mean X − mean Y | P(X > Y) | p (two-sided) |",
             "|---|---|---:|---|---|---|---:|---:|---:|"]
    for p in pairs:
        r = p.result
        lines.append(f"| `{p.mode}` | `{p.task}` | {p.fraction:.1f}T | {p.x} | {p.y} | {r.n_x}, {r.n_y} | "
                     f"{r.mean_x - r.mean_y:+.1f} | {r.p_improvement:.2f} | {r.p_value:.3f}"
                     f"{'' if r.exact else ' (permutations)'} |")
    return "\n".join(lines) + "\n"


def write_csv(pairs: list[Pair], path: str) -> str:
    return atomic_write_csv(path, COLUMNS, (
        [p.mode, p.task, f"{p.fraction:.1f}", p.x, p.y, p.result.n_x, p.result.n_y, f"{p.result.mean_x:.6g}",
         f"{p.result.mean_y:.6g}", f"{p.result.mean_x - p.result.mean_y:.6g}", f"{p.result.p_improvement:.6g}",
         f"{p.result.p_value:.6g}", int(p.result.exact)] for p in pairs))
