"""What ``imssr analyze`` writes: the per-state CSV, the rank correlations, the figure, the montage."""
from __future__ import annotations

from typing import Sequence

import numpy as np

from imssr.files import atomic_write_csv
from imssr.plots import pyplot
from imssr.plots.media import save_png


def spearman_ci(x: np.ndarray, y: np.ndarray, reps: int = 1000, seed: int = 0,
                level: float = 0.95) -> dict[str, float]:
    """Spearman's rank correlation of ``x`` and ``y`` (pairs with a NaN left out), its p-value
    (:func:`scipy.stats.spearmanr`) and a percentile bootstrap CI: ``reps`` resamples of the
    pairs with replacement from a generator seeded with ``seed``; resamples in which either
    variable is constant have no correlation and are skipped."""
    import warnings

    from scipy.stats import DegenerateDataWarning, bootstrap, rankdata, spearmanr

    keep = np.isfinite(x) & np.isfinite(y)
    x, y = np.asarray(x, float)[keep], np.asarray(y, float)[keep]
    out = {"n": int(len(x)), "rho": np.nan, "p": np.nan, "ci_low": np.nan, "ci_high": np.nan}
    if len(x) < 3 or np.ptp(x) == 0 or np.ptp(y) == 0:
        return out
    res = spearmanr(x, y)
    out["rho"], out["p"] = float(res.statistic), float(res.pvalue)

    def rank_correlation(xs: np.ndarray, ys: np.ndarray, axis: int = -1) -> np.ndarray:
        # Spearman = Pearson of the ranks (ties averaged), one resample per row; NaN for a
        # resample in which either variable is constant.
        rx, ry = rankdata(xs, axis=axis), rankdata(ys, axis=axis)
        rx -= rx.mean(axis=axis, keepdims=True)
        ry -= ry.mean(axis=axis, keepdims=True)
        den = np.sqrt((rx ** 2).sum(axis=axis) * (ry ** 2).sum(axis=axis))
        with np.errstate(invalid="ignore", divide="ignore"):
            return np.where(den > 0, (rx * ry).sum(axis=axis) / den, np.nan)

    with warnings.catch_warnings():
        # A degenerate resample makes scipy's own interval NaN; the interval below skips it.
        warnings.simplefilter("ignore", DegenerateDataWarning)
        boot = bootstrap((x, y), rank_correlation, n_resamples=reps, paired=True, vectorized=True,
                         method="percentile", confidence_level=level, rng=np.random.default_rng(seed))
    rho = boot.bootstrap_distribution[np.isfinite(boot.bootstrap_distribution)]
    if len(rho):
        tail = 100 * (1 - level) / 2
        out["ci_low"], out["ci_high"] = (float(v) for v in np.percentile(rho, [tail, 100 - tail]))
    return out


def write_rows(path: str, rows: list[dict]) -> str:
    """``rows`` (dicts with the same keys) as a CSV, atomically; NaN as an empty cell."""
    header = list(rows[0])

    def cell(v):
        return ("" if not np.isfinite(v) else f"{v:.6g}") if isinstance(v, float) else v

    return atomic_write_csv(path, header, ([cell(r[k]) for k in header] for r in rows))


def plot_correlations(rows: list[dict], corr: list[dict], modes: Sequence[str], path: str, title: str) -> str:
    """One row of panels per checkpoint: the intrinsic signal against novelty and against the
    nuisance distance of each scene, each panel titled with Spearman's rho and its CI."""
    plt = pyplot()
    steps = sorted({r["checkpoint_step"] for r in rows})
    xs = ["novelty"] + [f"nuisance_{m}" for m in modes]
    labels = {"novelty": "novelty (k-NN distance, std. physics units)"}
    labels.update({f"nuisance_{m}": f"nuisance distance, {m}" for m in modes})
    fig, axes = plt.subplots(len(steps), len(xs), figsize=(3.4 * len(xs), 2.9 * len(steps) + 0.5), squeeze=False)
    for i, step in enumerate(steps):
        sub = [r for r in rows if r["checkpoint_step"] == step]
        y = np.array([r["signal"] for r in sub], float)
        for j, key in enumerate(xs):
            ax = axes[i, j]
            x = np.array([r[key] for r in sub], float)
            ax.scatter(x, y, s=9, alpha=0.7)
            c = next(c for c in corr if c["checkpoint_step"] == step and c["against"] == key)
            ax.set_title(f"step {step:,}: rho {c['rho']:.2f} [{c['ci_low']:.2f}, {c['ci_high']:.2f}]", fontsize=9)
            if i == len(steps) - 1:
                ax.set_xlabel(labels[key], fontsize=8)
            if j == 0:
                ax.set_ylabel("intrinsic signal (raw loss of o')", fontsize=8)
            ax.tick_params(labelsize=7)
    fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    return save_png(fig, path)


def save_extremes(high: list[tuple[np.ndarray, str]], low: list[tuple[np.ndarray, str]], path: str, title: str) -> str:
    """The top-k highest-bonus states (top row) above the k lowest (bottom row): ``(H, W, 3)``
    frames with their captions, as a PNG."""
    cols = max(len(high), len(low), 1)
    fig, axes = pyplot().subplots(2, cols, figsize=(2.3 * cols, 5.4), squeeze=False)
    for ax in axes.flat:
        ax.axis("off")
    for row, items in enumerate((high, low)):
        for ax, (frame, caption) in zip(axes[row], items):
            ax.imshow(frame, interpolation="nearest")
            ax.set_title(caption, fontsize=8)
    fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    return save_png(fig, path)
