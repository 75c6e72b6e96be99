"""Sweep figures: learning curves across seeds, and final return against beta_0."""
from __future__ import annotations

import math
from typing import Optional

import numpy as np

from imssr.plots import pyplot, steps_axis
from imssr.plots.media import save_png
from imssr.report.results import SweepResults
from imssr.report.tables import Row, label_order, mode_order


def _grid(plt, n: int):
    cols = min(3, n)
    rows = -(-n // cols)
    fig, axes = plt.subplots(rows, cols, figsize=(4.2 * cols, 3.2 * rows), dpi=100, squeeze=False)
    for ax in axes.flat[n:]:
        ax.axis("off")
    return fig, list(axes.flat[:n])


def plot_curves(results: SweepResults, path: str) -> str:
    """One panel per (task, mode), one line per algo: mean over seeds with a ±std band, against
    agent steps (frames on the top axis when the task's runs share an action repeat)."""
    plt = pyplot()
    panels = [(task, mode) for task in sorted({r.run.task for r in results.runs})
              for mode in mode_order(m for r in results.runs if r.run.task == task for m, *_ in r.evals)]
    if not panels:
        panels = [(sorted({r.run.task for r in results.runs})[0], "training")]
    labels = label_order(results)
    colors = {label: plt.cm.tab10(i % 10) for i, label in enumerate(labels)}
    # Returns by (task, mode, label) and agent step, from one pass over the runs (a pass per curve
    # would cost curves x runs).
    returns: dict[tuple[str, str, str], dict[int, list[float]]] = {}
    for result in results.runs:
        for mode, step, _, ret in result.evals:
            returns.setdefault((result.run.task, mode, result.label), {}).setdefault(step, []).append(ret)
    fig, axes = _grid(plt, len(panels))
    for ax, (task, mode) in zip(axes, panels):
        for label in labels:
            by_step = returns.get((task, mode, label))
            if not by_step:
                continue
            x = sorted(by_step)
            m, s = (np.array([statistic(by_step[step]) for step in x]) for statistic in (np.mean, np.std))
            seeds = max(map(len, by_step.values()))
            ax.plot(x, m, marker="o", markersize=3, color=colors[label],
                    label=f"{label} ({seeds} {'seed' if seeds == 1 else 'seeds'})")
            ax.fill_between(x, m - s, m + s, color=colors[label], alpha=0.2, linewidth=0)
        ax.set_title(f"{task} ({mode})", fontsize=10)
        steps_axis(ax, results.action_repeat(task), small=True)
        ax.set_ylabel("evaluation return")
        ax.grid(alpha=0.3)
        if ax.get_legend_handles_labels()[0]:
            ax.legend(fontsize=7)
    fig.tight_layout()
    return save_png(fig, path)


def plot_beta(rows: list[Row], path: str) -> Optional[str]:
    """Final return (1.0T; mean ± std over seeds) against beta_0 on a log axis, per task and mode;
    base algos and beta_0 = 0 as horizontal reference lines with their ±std band."""
    swept = [r for r in rows if r.beta0 is not None and r.cells[-1].n]
    if not swept:
        return None
    plt = pyplot()
    panels = sorted({(r.task, r.mode) for r in swept}, key=lambda p: (p[0], p[1] != "training", p[1]))
    fig, axes = _grid(plt, len(panels))
    for ax, (task, mode) in zip(axes, panels):
        group = [r for r in rows if r.task == task and r.mode == mode and r.cells[-1].n]
        algos = sorted({r.algo for r in group if r.beta0 is not None})
        for i, algo in enumerate(algos):
            pts = sorted((r.beta0, r.cells[-1].mean, r.cells[-1].std)
                         for r in group if r.algo == algo and r.beta0 is not None and r.beta0 > 0)
            color = plt.cm.tab10(i % 10)
            if pts:
                ax.errorbar([p[0] for p in pts], [p[1] for p in pts], yerr=[p[2] for p in pts], marker="o",
                            capsize=3, color=color, label=algo)
            for r in group:
                if r.algo == algo and r.beta0 == 0:
                    _reference(ax, r, f"{algo} beta0=0", color)
        for j, r in enumerate(x for x in group if x.beta0 is None):
            _reference(ax, r, f"{r.label} (beta0 = 0)", plt.cm.tab10((len(algos) + j) % 10))
        ax.set_xscale("log")
        ax.set_xlabel("beta_0 (log scale)")
        ax.set_ylabel(f"return at 1.0T (step {group[0].cells[-1].step:,})")
        ax.set_title(f"{task} ({mode})", fontsize=10)
        ax.grid(alpha=0.3, which="both")
        ax.legend(fontsize=7)
    fig.tight_layout()
    return save_png(fig, path)


def _reference(ax, row: Row, label: str, color) -> None:
    cell = row.cells[-1]
    ax.axhline(cell.mean, color=color, linestyle="--", label=label)
    if not math.isnan(cell.std) and cell.std > 0:
        ax.axhspan(cell.mean - cell.std, cell.mean + cell.std, color=color, alpha=0.12)
