"""Learning-curve figures from a run's ``eval.csv``."""
from __future__ import annotations

import os

import numpy as np

from imssr.errors import ImssrError
from imssr.files import read_csv
from imssr.plots import pyplot, steps_axis
from imssr.plots.media import save_png
from imssr.rundir import RunDir, as_run_dir


def plot_learning_curve(run_dir: RunDir | str, out_path: str | None = None) -> str:
    """Plot the run's evaluation return (mean ± std over episodes) against agent steps, with
    environment frames on the top axis when the run's config gives the action repeat; returns
    the PNG's path (``out_path``, default ``RUN/learning_curve.png``)."""
    plt = pyplot()
    run = as_run_dir(run_dir)
    rows = read_csv(run.eval_log, complete_only=True)
    if not rows:
        raise ImssrError(f"no evaluations in {run.eval_log}")
    title = os.path.basename(os.path.abspath(run.path))
    action_repeat = None
    if run.has_config():
        cfg = run.read_config()
        title = f"{cfg.algo} on {cfg.env.task} (seed {cfg.train.seed})"
        action_repeat = cfg.env.action_repeat
    curves = _curves(rows, run.eval_log)
    fig, ax = plt.subplots(figsize=(6, 4), dpi=110)
    for mode in sorted(curves):
        x, m, s = (np.array(column) for column in zip(*sorted(curves[mode])))
        ax.plot(x, m, marker="o", label=mode)
        ax.fill_between(x, m - s, m + s, alpha=0.2)
    steps_axis(ax, action_repeat, "environment frames")
    ax.set_ylabel("evaluation return")
    ax.set_title(title)
    ax.grid(alpha=0.3)
    ax.legend()
    fig.tight_layout()
    return save_png(fig, out_path or run.learning_curve_path)


def _curves(rows: list[dict], path: str) -> dict[str, list[tuple[int, float, float]]]:
    """``(agent step, return mean, return std)`` of each scene's evaluations in ``eval.csv``'s ``rows``; a row that
    does not hold them is a one-line error that names it (rows count from 1 after the header of ``path``)."""
    curves: dict[str, list[tuple[int, float, float]]] = {}
    for number, r in enumerate(rows, start=1):
        try:
            mode = r["mode"]
            point = (int(float(r["step"])), float(r["return_mean"]), float(r["return_std"]))
            if not isinstance(mode, str):
                raise TypeError(mode)
        except (KeyError, TypeError, ValueError, OverflowError):
            raise ImssrError(f"row {number} of {path} is not an evaluation row (numbers in step, return_mean "
                             "and return_std, and a mode)") from None
        curves.setdefault(mode, []).append(point)
    return curves
