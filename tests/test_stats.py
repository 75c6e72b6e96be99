"""imssr.report.stats: the sample std, the Mann-Whitney permutation test with its effect size,
and Welch's interval, against scipy where scipy computes the same thing."""
import math

import numpy as np
import pytest
from scipy import stats as sp

from imssr.report.stats import compare, sample_std, welch_interval


def test_sample_std_is_ddof_1_and_none_for_one_seed():
    assert sample_std([100, 200, 300]) == pytest.approx(100.0)
    assert math.isnan(sample_std([5.0]))


@pytest.mark.parametrize("n_x, n_y", [(3, 3), (5, 5), (8, 7), (4, 9)])
def test_the_exact_test_is_scipys_without_ties(n_x, n_y):
    rng = np.random.default_rng(n_x * 10 + n_y)
    for _ in range(5):
        x, y = rng.normal(size=n_x), rng.normal(0.7, size=n_y)
        ours = compare(x, y)
        theirs = sp.mannwhitneyu(x, y, alternative="two-sided", method="exact")
        assert ours.exact and ours.p_value == pytest.approx(theirs.pvalue, abs=1e-12)
        assert ours.p_improvement == pytest.approx(theirs.statistic / (n_x * n_y))


def test_three_seeds_against_three_can_never_reach_p_below_0_1():
    c = compare([10, 11, 12], [1, 2, 3])
    assert (c.p_improvement, c.p_value) == (1.0, pytest.approx(0.1))


def test_ties_count_half_and_identical_sets_give_p_1():
    c = compare([1, 1, 2], [1, 2, 2])
    assert c.p_improvement == pytest.approx((0.5 + 0.5 + 1 + 0.5 + 0.5) / 9)  # 1s tie, 2 beats 1, 2s tie
    assert compare([3, 3, 3], [3, 3, 3]).p_value == 1.0


def test_large_sets_use_seeded_permutations_close_to_the_exact_p():
    rng = np.random.default_rng(7)
    x, y = rng.normal(size=14), rng.normal(0.8, size=13)
    ours = compare(x, y)
    assert not ours.exact and ours == compare(x, y)  # reproducible
    assert ours.p_value == pytest.approx(sp.mannwhitneyu(x, y, alternative="two-sided", method="exact").pvalue,
                                         abs=0.01)


def test_welch_interval_is_scipys():
    rng = np.random.default_rng(3)
    x, y = rng.normal(5, 2, size=4), rng.normal(3, 1, size=9)
    diff, low, high = welch_interval(x.mean(), x.std(ddof=1), 4, y.mean(), y.std(ddof=1), 9)
    ci = sp.ttest_ind(x, y, equal_var=False).confidence_interval(0.95)
    assert (diff, low, high) == pytest.approx((x.mean() - y.mean(), ci.low, ci.high))
    assert welch_interval(1.0, float("nan"), 1, 2.0, 1.0, 5) is None
