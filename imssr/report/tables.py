"""The paper's table layout: mean ± std over seeds at 0.2T, 0.5T and 1.0T per task and mode.

T counts agent steps, as the paper's does, whatever the task's action repeat.  The point of a fraction ``f`` is the
first agent step at or after ``f * T``, and a seed's value there is its last evaluation at or before it (the paper's
10,000-step interval divides its points).  A seed whose evaluations stop before the point has no value there, and the
cell says how many of the expected seeds it averages, and how many of those failed ("(2/3, 1 failed)").
"""
from __future__ import annotations

import csv
import math
from dataclasses import dataclass, field
from fractions import Fraction
from typing import Optional

import numpy as np

from imssr.errors import ImssrError
from imssr.files import atomic_write_csv
from imssr.presets import ALGOS
from imssr.report.results import RunResult, SweepResults
from imssr.report.stats import sample_std, welch_interval
from imssr.sweep.directory import PlannedRun

FRACTIONS = (0.2, 0.5, 1.0)
TABLE_COLUMNS = ["mode", "task", "label", "algo", "beta0", "fraction", "step", "frame", "mean", "std",
                 "seeds", "expected_seeds", "failed_seeds", "best", "paper_mean", "paper_std", "paper_seeds",
                 "paper_diff", "paper_diff_low", "paper_diff_high", "precision", "per_seed"]


@dataclass(frozen=True)
class PaperNumber:
    """A published mean ± std over seeds."""

    mean: float
    std: float
    seeds: Optional[int]
    """Seeds behind it, where the source says (None: not stated)."""
    source: str
    """Where it was published, e.g. "IM-SSR paper, Table I"."""


@dataclass
class Cell:
    """Mean ± std over seeds of one (mode, task, label) at one fraction of T."""

    fraction: float
    """Fraction of the budget T."""
    step: int
    """The point: the first agent step at or after ``fraction * T``."""
    frame: Optional[int]
    """The point in environment frames (None when the task's runs differ in action repeat)."""
    values: dict[int, float] = field(default_factory=dict)
    """Seed -> return of its evaluation at the point."""
    expected: int = 0
    """Seeds the sweep planned (or that any algo of the task ran) for this group."""
    failed: set[int] = field(default_factory=set)
    """Seeds without a value here whose run failed (``sweep_status.json`` or its ``status.json``)."""
    best: bool = False
    """Highest mean of its (mode, task) row group at this fraction."""
    paper: Optional[PaperNumber] = None
    """The published number for the same algo, task, mode and fraction, if any."""

    @property
    def n(self) -> int:
        return len(self.values)

    @property
    def mean(self) -> float:
        return float(np.mean(list(self.values.values()))) if self.values else math.nan

    @property
    def std(self) -> float:
        """Sample standard deviation over seeds (ddof 1; NaN below two seeds)."""
        return sample_std(list(self.values.values()))

    def against_paper(self) -> Optional[tuple[float, float, float]]:
        """``(ours - published, low, high)``: the difference of means and its 95% Welch interval;
        None without a published number with its seeds, or with fewer than two seeds here."""
        if self.paper is None or self.paper.seeds is None:
            return None
        return welch_interval(self.mean, self.std, self.n, self.paper.mean, self.paper.std, self.paper.seeds)


@dataclass
class Row:
    """One algo (or algo at one beta_0) on one task in one mode: a cell per fraction."""

    mode: str
    task: str
    label: str
    algo: str
    beta0: Optional[float]
    cells: list[Cell]
    precision: str = "fp32"
    """``agent.precision`` of the row's runs (fp32 and bf16 runs are separate rows)."""


def point_step(fraction: float, budget: int) -> int:
    """The agent step of ``fraction * budget``, rounded up (exactly: 0.2 * 125 is 25, not 25.000001)."""
    return math.ceil(Fraction(str(fraction)) * budget)


def value_at(evals: list[tuple[int, float]], point: int) -> Optional[float]:
    """Return of the last evaluation ``(step, return)`` at or before agent step ``point``;
    None when the run's evaluations have not reached the point."""
    evals = sorted(evals)
    if not evals or evals[-1][0] < point:
        return None
    before = [ret for step, ret in evals if step <= point]
    return before[-1] if before else None


def _why_missing(evals: list[tuple[int, float]], point: int) -> str:
    if not evals:
        return "no evaluation in this mode"
    steps = sorted(s for s, _ in evals)
    if steps[-1] < point:
        return f"not reached: last evaluation at step {steps[-1]}"
    return f"no evaluation at or before it: first at step {steps[0]}"


def mode_order(modes) -> list[str]:
    """The training scene first, then the test scenes alphabetically."""
    return sorted(set(modes), key=lambda m: (m != "training", m))


def label_order(results: SweepResults) -> list[str]:
    """fp32 before other precisions; within each, algos in registry order (curl, im-curl, ...),
    beta sweeps by increasing beta_0."""
    rank = {name: i for i, name in enumerate(ALGOS)}
    keys = {(r.label, r.run.algo, r.run.beta0, r.precision) for r in (*results.runs, *results.planned)}
    ordered = sorted(keys, key=lambda k: (k[3] != "fp32", k[3], rank.get(k[1], len(rank)), k[1],
                                          -1.0 if k[2] is None else k[2]))
    return [k[0] for k in ordered]


def build_rows(results: SweepResults, paper: Optional[dict] = None) -> tuple[list[Row], list[str]]:
    """Every (mode, task, label) row, and notes on missing seeds and evaluation points."""
    notes: list[str] = []
    labels = label_order(results)
    runs_of: dict[tuple[str, str], list[RunResult]] = {}
    for result in results.runs:
        runs_of.setdefault((result.run.task, result.label), []).append(result)
    planned_of: dict[tuple[str, str], list[PlannedRun]] = {}
    for p in results.planned:
        planned_of.setdefault((p.run.task, p.label), []).append(p)
    rows = []
    for task in sorted({r.run.task for r in results.runs}):
        budget = results.budget(task)
        expected = _expected_seeds(results, task)
        for mode in mode_order(m for r in results.runs if r.run.task == task for m, *_ in r.evals):
            for label in labels:
                runs, planned = runs_of.get((task, label), []), planned_of.get((task, label), [])
                if not runs and not planned:
                    continue
                first = (runs or planned)[0]
                algo, beta0 = first.run.algo, first.run.beta0
                want, ran = expected.get(label, set()), {r.run.seed for r in runs}
                # Planned runs that failed before writing their config.json.
                failed_early = {p.run.seed: results.failure(p.run) for p in planned
                                if p.run.seed in want - ran and results.failure(p.run)}
                absent = sorted(want - ran - set(failed_early))
                cells = []
                for fraction in FRACTIONS:
                    point = point_step(fraction, budget)
                    cell = Cell(fraction, point, results.frames_at(task, point), expected=len(want | ran),
                                failed=set(failed_early))
                    late = []
                    for result in runs:
                        evals = [(s, v) for m, s, _, v in result.evals if m == mode]
                        value = value_at(evals, point)
                        failure = results.failure(result.run)
                        if value is not None:
                            cell.values[result.run.seed] = value
                            continue
                        why = f"failed: {failure}" if failure else _why_missing(evals, point)
                        late.append(f"{result.run.seed} ({why})")
                        if failure:
                            cell.failed.add(result.run.seed)
                    parts = ([f"no value for seed(s) {', '.join(late)}"] if late else []) + \
                            ([f"no run for seed(s) {', '.join(map(str, absent))}"] if absent else []) + \
                            [f"seed {s} failed before writing anything ({e})" for s, e in failed_early.items()]
                    if parts:
                        notes.append(f"{mode} / {task} / {label} at {fraction:.1f}T (step {point}): "
                                     + "; ".join(parts))
                    if paper is not None and beta0 is None and algo in ALGOS:
                        cell.paper = paper.get((task, mode, fraction, ALGOS[algo].paper_name))
                    cells.append(cell)
                rows.append(Row(mode, task, label, algo, beta0, cells, first.precision))
    _mark_best(rows)
    return rows, notes


def _expected_seeds(results: SweepResults, task: str) -> dict[str, set[int]]:
    """Seeds each label should have on ``task``: the plan's, else every seed any label ran."""
    planned = [p for p in results.planned if p.run.task == task]
    if planned:
        out: dict[str, set[int]] = {}
        for p in planned:
            out.setdefault(p.label, set()).add(p.run.seed)
        return out
    seeds = {r.run.seed for r in results.runs if r.run.task == task}
    return {r.label: seeds for r in results.runs if r.run.task == task}


def _mark_best(rows: list[Row]) -> None:
    scored: dict[tuple[str, str, int], list[Cell]] = {}  # (mode, task, fraction's index) -> cells with seeds
    for row in rows:
        for i, cell in enumerate(row.cells):
            if cell.n:
                scored.setdefault((row.mode, row.task, i), []).append(cell)
    for cells in scored.values():
        top = max(cell.mean for cell in cells)
        for cell in cells:
            cell.best = cell.mean == top


# -- the published numbers ---------------------------------------------------------------
PAPER_DATASETS = {
    "imssr-paper": ("imssr_paper.csv", "the IM-SSR paper's Tables I and II (T = 500,000 agent steps)"),
    "curl-dmc100k": ("curl_dmc100k.csv", "the CURL paper's Table 1, DMControl-100k (100,000 frames)"),
}
"""Published numbers shipped with imssr (``imssr/report/data/``): name -> (file, what it holds)."""
DEFAULT_PAPER = "imssr-paper"


def load_paper_results(spec: Optional[str] = None) -> dict[tuple[str, str, float, str], PaperNumber]:
    """``(task, mode, fraction, paper algo name) -> PaperNumber`` from ``spec``: a shipped dataset's name
    (:data:`PAPER_DATASETS`; None: :data:`DEFAULT_PAPER`) or the path of a CSV (columns ``table, task, mode,
    frames_fraction, algorithm, mean, std`` and, optionally, ``seeds``)."""
    from importlib import resources

    spec = spec or DEFAULT_PAPER
    try:
        if spec in PAPER_DATASETS:
            text = (resources.files("imssr.report") / "data" / PAPER_DATASETS[spec][0]).read_text(encoding="utf-8")
        else:
            with open(spec, encoding="utf-8") as fh:
                text = fh.read()
    except FileNotFoundError:
        raise ImssrError(f"paper results not found: {spec} (a CSV file, or one of "
                         f"{', '.join(PAPER_DATASETS)})") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise ImssrError(f"cannot read paper results {spec}: {exc}") from None
    out = {}
    for row in csv.DictReader(text.splitlines()):
        try:
            key = (row["task"], row["mode"], float(row["frames_fraction"]), row["algorithm"])
            seeds = row.get("seeds") or None
            out[key] = PaperNumber(float(row["mean"]), float(row["std"]), int(seeds) if seeds else None,
                                   row.get("table") or "")
        except (KeyError, TypeError, ValueError):
            continue
    return out


# -- output ------------------------------------------------------------------------------
def _fmt(mean: float, std: float) -> str:
    return f"{mean:.1f} ± {'–' if math.isnan(std) else f'{std:.1f}'}"


def paper_text(paper: PaperNumber) -> str:
    """``"582.0 ± 146.0 (n = 10)"``; the n only where the source states it."""
    return _fmt(paper.mean, paper.std) + ("" if paper.seeds is None else f" (n = {paper.seeds})")


def cell_text(cell: Cell) -> str:
    failed = f", {len(cell.failed)} failed" if cell.failed else ""
    if not cell.n:
        return f"– (0/{cell.expected}{failed})"
    text = _fmt(cell.mean, cell.std)
    if cell.best:
        text = f"**{cell.mean:.1f}**" + text[len(f"{cell.mean:.1f}"):]
    return text if cell.n >= cell.expected and not failed else f"{text} ({cell.n}/{cell.expected}{failed})"


def per_seed_text(cell: Cell, sep: str = ", ") -> str:
    """Each seed's return at the point, in seed order: ``"1: 512.3, 2: 601.0"``."""
    return sep.join(f"{seed}: {cell.values[seed]:.1f}" for seed in sorted(cell.values))


def markdown_points(results: SweepResults) -> str:
    """Where 0.2T, 0.5T and 1.0T fall on each task, in agent steps with the frames beside."""
    lines = ["| task | action repeat | " + " | ".join(f"{f:.1f}T" for f in FRACTIONS) + " |",
             "|---|---:|" + "---:|" * len(FRACTIONS)]
    for task in sorted({r.run.task for r in results.runs}):
        budget, repeat = results.budget(task), results.action_repeat(task)
        repeats = str(repeat) if repeat is not None else \
            ", ".join(map(str, sorted({r.action_repeat for r in results.runs if r.run.task == task})))
        points = [(p, results.frames_at(task, p)) for p in (point_step(f, budget) for f in FRACTIONS)]
        lines.append(f"| `{task}` | {repeats} | " + " | ".join(
            f"{p:,} steps ({'frames vary' if frame is None else f'{frame:,} frames'})" for p, frame in points) + " |")
    return "\n".join(lines) + "\n"


def markdown_tables(rows: list[Row], results: SweepResults, with_paper: bool) -> str:
    """One table per mode: tasks as row groups, a column per fraction (and the paper's beside it)."""
    out = []
    for mode in mode_order(r.mode for r in rows):
        mode_rows = [r for r in rows if r.mode == mode]
        header = ["task", "algo"]
        for fraction in FRACTIONS:
            header.append(f"{fraction:.1f}T")
            if with_paper:
                header.append(f"paper {fraction:.1f}T")
        header += [f"per seed at {FRACTIONS[-1]:.1f}T", "seeds"]
        budgets = sorted({results.budget(r.task) for r in mode_rows})
        out.append(f"### `{mode}` (T = {', '.join(f'{b:,}' for b in budgets)} agent steps)\n")
        out.append("| " + " | ".join(header) + " |")
        out.append("|" + "|".join(["---"] * 2 + ["---:"] * (len(header) - 2)) + "|")
        previous_task = None
        for row in mode_rows:
            task = f"`{row.task}`" if row.task != previous_task else ""
            previous_task = row.task
            cols = [task, row.label]
            for cell in row.cells:
                cols.append(cell_text(cell))
                if with_paper:
                    cols.append(paper_text(cell.paper) if cell.paper else "")
            final = row.cells[-1]
            cols += [per_seed_text(final),
                     f"{final.n}/{final.expected}" + (f", {len(final.failed)} failed" if final.failed else "")]
            out.append("| " + " | ".join(cols) + " |")
        out.append("")
    return "\n".join(out)


def markdown_against_paper(rows: list[Row]) -> str:
    """Each cell with a published number: ours and theirs with n, the difference and its interval."""
    lines = ["| mode | task | algo | T | ours: mean ± std (n) | published: mean ± std (n) | "
             "difference, 95% Welch interval |", "|---|---|---|---:|---:|---:|---|"]
    for row in rows:
        for cell in row.cells:
            if cell.paper is None or not cell.n:
                continue
            diff = cell.against_paper()
            why = "no interval: the source gives no seed count" if cell.paper.seeds is None else \
                "no interval: fewer than two seeds"
            lines.append(f"| `{row.mode}` | `{row.task}` | {row.label} | {cell.fraction:.1f}T | "
                         f"{_fmt(cell.mean, cell.std)} ({cell.n}) | {paper_text(cell.paper)} | "
                         + (why if diff is None else f"{diff[0]:+.1f} [{diff[1]:+.1f}, {diff[2]:+.1f}]") + " |")
    return "\n".join(lines) + "\n" if len(lines) > 2 else ""


def write_table_csv(rows: list[Row], path: str) -> str:
    def lines():
        for row in rows:
            for cell in row.cells:
                p = cell.paper
                paper = ["", "", ""] if p is None else [f"{p.mean:g}", f"{p.std:g}", "" if p.seeds is None else p.seeds]
                diff = cell.against_paper() if cell.n else None
                yield [row.mode, row.task, row.label, row.algo, "" if row.beta0 is None else row.beta0,
                       f"{cell.fraction:.1f}", cell.step, "" if cell.frame is None else cell.frame,
                       "" if not cell.n else f"{cell.mean:.6g}",
                       "" if not cell.n or math.isnan(cell.std) else f"{cell.std:.6g}", cell.n, cell.expected,
                       len(cell.failed), int(cell.best), *paper,
                       *(["", "", ""] if diff is None else [f"{v:.6g}" for v in diff]), row.precision,
                       per_seed_text(cell, sep=";").replace(": ", ":")]

    return atomic_write_csv(path, TABLE_COLUMNS, lines())
