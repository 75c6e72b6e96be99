"""The statistics a report states, chosen for what a few seeds can carry.

- Spread: the sample standard deviation (ddof 1); with one seed there is none.
- Two sets of runs: P(X > Y) = U / (n_x n_y), ties counted half (rliable's "probability of
  improvement" on one task), and the two-sided Mann-Whitney p-value, a permutation test of U.
  With three seeds against three the smallest p is 0.1, so the report gives n beside every p.
- Against a published mean: the difference of means and its 95% Welch interval, never "inside
  the published spread", which almost any result is when the spread is a std over seeds.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from itertools import combinations
from typing import Optional, Sequence

import numpy as np

EXACT_SPLITS = 200_000
"""Up to this many splits of the pooled runs the permutation test enumerates them all."""
PERMUTATIONS = 20_000
"""Random splits when there are more (seeded: a report is reproducible)."""
MIN_SEEDS_FOR_BOOTSTRAP = 5
"""Fewest seeds per task for an IQM and a bootstrap interval: below it the IQM of n values is their mean (n = 3: the
middle value's neighbours average in) and a bootstrap interval is little more than [min, max]."""


def sample_std(values: Sequence[float]) -> float:
    """Standard deviation with ddof 1 (NaN for fewer than two values)."""
    return float(np.std(values, ddof=1)) if len(values) >= 2 else math.nan


@dataclass(frozen=True)
class Comparison:
    """Two sets of runs at one point: X against Y."""

    n_x: int
    n_y: int
    mean_x: float
    mean_y: float
    p_improvement: float
    """P(X > Y): the fraction of (x, y) pairs with x > y, ties counted half."""
    p_value: float
    """Two-sided Mann-Whitney (permutation) p-value."""
    exact: bool
    """Whether every split was enumerated (else :data:`PERMUTATIONS` random ones)."""


def compare(x: Sequence[float], y: Sequence[float], seed: int = 0) -> Comparison:
    """P(X > Y) and the two-sided permutation p-value of the Mann-Whitney U of ``x`` against ``y``."""
    from scipy.stats import rankdata  # scikit-learn's dependency: always installed

    x, y = np.asarray(x, dtype=float), np.asarray(y, dtype=float)
    if not len(x) or not len(y):
        raise ValueError("compare() needs at least one value on each side")
    pooled = np.concatenate([x, y])
    n, k = len(pooled), len(x)
    ranks = rankdata(pooled)  # tied values share the mean of their ranks
    centre = k * (n + 1) / 2  # the rank sum of x under no difference
    observed = abs(ranks[:k].sum() - centre)
    exact = math.comb(n, k) <= EXACT_SPLITS
    if exact:
        sums = ranks[np.array(list(combinations(range(n), k)))].sum(axis=1)
    else:
        rng = np.random.default_rng(seed)
        sums = np.array([ranks[rng.permutation(n)[:k]].sum() for _ in range(PERMUTATIONS)])
    extreme = int(np.sum(np.abs(sums - centre) >= observed - 1e-9))
    p = extreme / len(sums) if exact else (extreme + 1) / (PERMUTATIONS + 1)
    u = ranks[:k].sum() - k * (k + 1) / 2
    return Comparison(len(x), len(y), float(x.mean()), float(y.mean()), float(u / (len(x) * len(y))), p, exact)


def welch_interval(mean_x: float, std_x: float, n_x: int, mean_y: float, std_y: float, n_y: int,
                   level: float = 0.95) -> Optional[tuple[float, float, float]]:
    """``(difference, low, high)`` of ``mean_x - mean_y`` with Welch's t interval; None when a side
    has fewer than two seeds or an unknown std."""
    if n_x < 2 or n_y < 2 or not (math.isfinite(std_x) and math.isfinite(std_y)):
        return None
    from scipy import stats  # scikit-learn's dependency: always installed

    vx, vy = std_x ** 2 / n_x, std_y ** 2 / n_y
    diff = mean_x - mean_y
    if vx + vy == 0:
        return diff, diff, diff
    dof = (vx + vy) ** 2 / (vx ** 2 / (n_x - 1) + vy ** 2 / (n_y - 1))
    half = float(stats.t.ppf(0.5 + level / 2, dof)) * math.sqrt(vx + vy)
    return diff, diff - half, diff + half
