"""``imssr report``: a sweep directory -> CSVs, the paper's table, curves, aggregates, beta_0 plot.

Files written under ``out``:

- ``evaluations.csv``  every evaluation of every seed (``algo,task,mode,seed,step,frame,return,beta0``)
- ``table.csv``        mean/std/seeds at 0.2T, 0.5T, 1.0T per (mode, task, algo), the published
                       numbers beside with the difference and its 95% Welch interval
- ``comparisons.csv``  per task: each algo with an intrinsic reward against its base, each
                       precision against fp32: n, P(X > Y) and the two-sided Mann-Whitney p
- ``aggregates.csv``   rliable IQM across tasks with 95% bootstrap CIs (5 seeds per task or more,
                       and rliable installed: the ``report`` extra)
- ``curves.png``       learning curves against agent steps, one panel per task and mode
- ``beta0.png``        final return against beta_0 (only for a beta sweep)
- ``report.md``        all of the above in one page, with the runs that failed and notes on what
                       is missing
"""
from __future__ import annotations

import os
from collections import Counter
from typing import Optional

from imssr.errors import ImssrError
from imssr.files import atomic_write_text
from imssr.report import aggregate, comparisons, figures, tables
from imssr.provenance import CODE_FIELDS, DEVICE_FIELDS, summary
from imssr.report.results import collect, write_evaluations
from imssr.report.stats import MIN_SEEDS_FOR_BOOTSTRAP

PAPER_T = 500_000
"""The paper's T in agent steps (Table III, "Number of training steps"), on every task."""


def write_report(root: str, out: str, paper_results: Optional[str] = None, reps: int = 2000) -> list[tuple[str, str]]:
    """Write the report; return ``(path, description)`` of each file written."""
    results = collect(root)
    notes = list(results.notes)
    try:
        paper = tables.load_paper_results(paper_results)
    except ImssrError as exc:
        if paper_results is None:
            raise
        paper = None
        notes.append(f"{exc}: no paper column")
    rows, row_notes = tables.build_rows(results, paper)
    notes += row_notes
    budgets = sorted({results.budget(t) for t in {r.run.task for r in results.runs}})
    # The IM-SSR paper's tables (shipped, or the spec's CSV naming them "I" and "II") are at its T.
    imssr_paper = paper is not None and any(p.source.startswith("IM-SSR") or p.source in ("I", "II")
                                            for p in paper.values())
    if imssr_paper and budgets != [PAPER_T]:
        paper_points = "/".join(f"{tables.point_step(f, PAPER_T):,}" for f in tables.FRACTIONS)
        notes.append(f"the paper's numbers are at T = {PAPER_T:,} agent steps (0.2T/0.5T/1.0T = "
                     f"{paper_points} steps); this sweep's T is {', '.join(f'{b:,}' for b in budgets)} "
                     f"agent steps, so its 0.2T/0.5T/1.0T are other agent steps")
    made_by, mixed = makers(results)
    notes += mixed
    aggregates, agg_notes = aggregate.compute(rows, reps=reps)
    notes += agg_notes
    pairs = comparisons.compute(rows)
    written = [
        (write_evaluations(results, os.path.join(out, "evaluations.csv")), "per-seed evaluations"),
        (tables.write_table_csv(rows, os.path.join(out, "table.csv")), "table (CSV)"),
        (comparisons.write_csv(pairs, os.path.join(out, "comparisons.csv")), "comparisons (CSV)"),
        (aggregate.write_csv(aggregates, os.path.join(out, "aggregates.csv")), "aggregate metrics (CSV)"),
        (figures.plot_curves(results, os.path.join(out, "curves.png")), "learning curves"),
    ]
    beta_png = figures.plot_beta(rows, os.path.join(out, "beta0.png")) if results.is_beta_sweep else None
    if beta_png:
        written.append((beta_png, "final return against beta_0"))
    # The root as the user named it: a committed report should not carry this machine's paths.
    md = _markdown(results, os.path.normpath(root), rows, aggregates, pairs, made_by, notes, paper is not None,
                   beta_png is not None, reps)
    path = os.path.join(out, "report.md")
    atomic_write_text(path, md)
    written.append((path, "report"))
    return written


def _markdown(results, root_name: str, rows, aggregates, pairs, made_by, notes, with_paper: bool,
              beta_plot: bool, reps: int) -> str:
    n_evals = sum(len(r.evals) for r in results.runs)
    failed = (f" **{len(results.failures)} failed** (see Failed runs)." if results.failures else "")
    against = tables.markdown_against_paper(rows) if with_paper else ""
    parts = [
        f"# Sweep report: `{root_name}`\n",
        f"{_count(len(results.runs), 'run')}, {_count(n_evals, 'evaluation')}.{failed} Cells: mean ± std over "
        "seeds (sample std, ddof 1; – for one seed) of each seed's last evaluation return at or before the point's "
        "agent step; **bold**: best mean of the task at that point; `(n/N)`: only n of the N expected seeds reached "
        "the point; `k failed`: k of them failed in the sweep; the last column: n per row."
        + (" `paper` columns: the published numbers, with their seeds where the source states them."
           if with_paper else "") + "\n",
        "## Table\n",
        "T is the budget in agent steps; each task's points in agent steps and environment frames:\n",
        tables.markdown_points(results),
        tables.markdown_tables(rows, results, with_paper),
    ]
    if against:
        parts += ["## Against the published numbers\n",
                  "The difference of means (ours minus published) with its 95% Welch interval, from each "
                  "side's std and seeds. A published std is the spread of seeds, not an interval for its "
                  "mean: a result \"inside the spread\" says little, the interval of the difference says how "
                  "far apart the two means may be.\n", against]
    parts += [
        "## Code and devices\n",
        "What made each row's runs (every start and resume of every run: `provenance.json`):\n",
        makers_markdown(made_by),
        "## Comparisons within a task\n",
        comparisons.markdown(pairs),
        "## Aggregate metrics (rliable)\n",
        f"Scores normalised by 1000 (the DMC maximum). IQM: interquartile mean over runs and tasks, with a "
        f"95% stratified-bootstrap CI ({reps} replicates), given only where every task has at least "
        f"{MIN_SEEDS_FOR_BOOTSTRAP} seeds.\n",
        aggregate.markdown(aggregates),
        "## Learning curves\n",
        "Evaluation return against agent steps (environment frames on the top axis).\n",
        "![learning curves](curves.png)\n",
    ]
    if beta_plot:
        parts += ["## Beta_0 sensitivity\n", "Return at 1.0T against beta_0 (log axis); dashed lines: the "
                  "base algorithms (beta_0 = 0).\n", "![beta_0](beta0.png)\n"]
    if results.failures:
        parts += ["## Failed runs\n", "Runs that failed, with the last error: those `sweep_status.json` lists as "
                  "failed after every attempt (the full output is in each run's `sweep.log`) and those whose own "
                  "last training failed or diverged (`status.json`); their evaluations up to the failure count where "
                  "they reach.\n", "\n".join(f"- `{os.path.relpath(d, results.root)}`: {e}"
                                             for d, e in sorted(results.failures.items())) + "\n"]
    parts += ["## Notes\n",
              "\n".join(f"- {n}" for n in notes) + "\n" if notes else "Every expected seed reached every point.\n"]
    return "\n".join(parts)


def makers(results) -> tuple[dict[tuple[str, str], Counter], list[str]]:
    """``(task, label) -> {one line of code and device: runs}`` over every record of every run (a run
    resumed elsewhere counts under both; runs without records under "not recorded"), and one warning
    per row whose runs were made by more than one code version or device."""
    made_by: dict[tuple[str, str], Counter] = {}
    versions: dict[tuple[str, str], set] = {}
    for result in results.runs:
        key = (result.run.task, result.label)
        lines = {summary(r) for r in result.provenance} or {"not recorded (a run of imssr before provenance.json)"}
        made_by.setdefault(key, Counter()).update(lines)
        versions.setdefault(key, set()).update(tuple(r.get(f) for f in (*CODE_FIELDS, *DEVICE_FIELDS))
                                               for r in result.provenance)
    return made_by, [f"warning: {task} / {label} mixes code versions or devices: " + "; ".join(
        f"{line} ({n} run{'s' if n > 1 else ''})" for line, n in sorted(made_by[task, label].items()))
        for (task, label), found in sorted(versions.items()) if len(found) > 1]


def makers_markdown(made_by: dict[tuple[str, str], dict[str, int]]) -> str:
    lines = ["| task | algo | code and device | runs |", "|---|---|---|---:|"]
    for (task, label), found in sorted(made_by.items()):
        for i, (line, n) in enumerate(sorted(found.items())):
            lines.append(f"| {'`' + task + '`' if i == 0 else ''} | {label if i == 0 else ''} | {line} | {n} |")
    return "\n".join(lines) + "\n"


def _count(n: int, noun: str) -> str:
    """``1 run``, ``3 runs``."""
    return f"{n:,} {noun}{'' if n == 1 else 's'}"
