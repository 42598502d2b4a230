"""sage/stats.py against hand computations and an independent stratified bootstrap."""
import math

import numpy as np
import pytest

from sage import stats


def test_iqm_is_the_mean_of_the_middle_half():
    assert stats.iqm([1, 2, 3, 4, 5, 6, 7, 8]) == pytest.approx(4.5)
    assert stats.iqm([0, 0, 0, 0, 1, 1, 1, 100]) == pytest.approx(0.5)   # the outlier is trimmed


def _hand_stratified_ci(groups, fn, n=20_000, seed=1, level=0.95):
    """Each group resampled within itself, ``n`` times (one row per resample), then pooled."""
    rng = np.random.default_rng(seed)
    pooled = np.concatenate([g[rng.integers(0, g.size, (n, g.size))] for g in groups], axis=1)
    return np.quantile(fn(pooled), [(1 - level) / 2, (1 + level) / 2])


def _hand_iqm(rows):
    """Mean of the middle half of each row, by sorting: 18 runs -> entries 4..13 (the 25%
    trimmed mean cuts int(0.25 * 18) = 4 from each end)."""
    k = int(0.25 * rows.shape[1])
    return np.sort(rows, axis=1)[:, k:rows.shape[1] - k].mean(axis=1)


def test_stratified_ci_matches_an_independent_resampler():
    rng = np.random.default_rng(0)
    groups = [rng.normal(mu, 1.0, 6) for mu in (0.0, 2.0, 5.0)]
    values = np.concatenate(groups)
    strata = sum(([k] * 6 for k in range(3)), [])
    for est, fn in (("mean", lambda rows: rows.mean(axis=1)), ("iqm", _hand_iqm)):
        out = stats.aggregate_ci(values, strata, est)
        hand = _hand_stratified_ci(groups, fn)
        assert out["estimate"] == pytest.approx(fn(values[None])[0])
        assert out["ci"] == pytest.approx(hand, abs=0.08)
        assert out["ci"][0] < out["estimate"] < out["ci"][1]
    # stratified: the scenario means are not resampled away, so the CI is narrower than pooling
    pooled = stats.aggregate_ci(values, [0] * 18, "mean")
    assert np.diff(stats.aggregate_ci(values, strata)["ci"]) < np.diff(pooled["ci"])


def test_ci_is_reproducible_and_nan_where_a_stratum_has_one_run():
    a = stats.aggregate_ci([0.1, 0.5, 0.9, 0.2], ["x", "x", "y", "y"])
    assert a == stats.aggregate_ci([0.1, 0.5, 0.9, 0.2], ["x", "x", "y", "y"])
    assert all(math.isnan(v) for v in stats.aggregate_ci([0.1, 0.5, 0.9], ["x", "x", "y"])["ci"])
    assert stats.aggregate_ci([1.0, 1.0, 0.0, 0.0], ["x", "x", "y", "y"])["ci"] == [0.5, 0.5]


def test_probability_of_improvement():
    hi, lo = [0.9, 0.8, 0.95], [0.1, 0.2, 0.3]
    assert stats.probability_of_improvement(hi, "aaa", lo, "aaa")["estimate"] == 1.0
    assert stats.probability_of_improvement(lo, "aaa", hi, "aaa")["estimate"] == 0.0
    assert stats.probability_of_improvement(hi, "aaa", hi, "aaa")["estimate"] == pytest.approx(0.5)
    # per scenario, then averaged: scenario a 1.0, scenario b 0.0 -> 0.5
    out = stats.probability_of_improvement([1, 1, 0, 0], "aabb", [0, 0, 1, 1], "aabb")
    assert out["estimate"] == 0.5 and out["scenarios"] == 2
    # one pair of four ties, three wins: (3 + 0.5) / 4
    assert stats.probability_of_improvement([1, 2], "aa", [1, 0], "aa")["estimate"] == pytest.approx(0.875)


def test_runs_needed_and_verdicts():
    # normal approximation ((1.95996 + 0.84162) * 0.5 / 0.1)^2 = 196.2; the t-test needs a few more
    n = stats.runs_needed(0.1, 0.5)
    assert 197 <= n <= 200 and stats.runs_needed(-0.1, 0.5) == n
    from scipy import stats as st
    for m, ok in ((n, True), (n - 1, False)):
        crit = st.t.ppf(0.975, m - 1) + st.t.ppf(0.8, m - 1)
        assert bool(crit * 0.5 / m ** 0.5 <= 0.1) == ok
    assert stats.runs_needed(0.5, 0.1) >= 2   # never fewer than two pairs
    assert stats.runs_needed(0.1, 0.0) is None and stats.runs_needed(0.0, 0.5) is None
    assert stats.verdict([0.01, 0.2], +1) == "confirmed" and stats.verdict([0.01, 0.2], -1) == "refuted"
    assert stats.verdict([-0.1, 0.2], +1) == "undecided" and stats.verdict([math.nan, 1], +1) == "undecided"


def test_paired_difference_reports_the_spread():
    pairs = {("a", 0): (1.0, 0.0), ("a", 1): (0.0, 0.0), ("b", 0): (1.0, 1.0), ("b", 1): (1.0, 0.0)}
    out = stats.paired_difference_ci(pairs)
    assert out["estimate"] == 0.5 and out["runs"] == 4
    assert out["sd"] == pytest.approx(np.std([1, 0, 0, 1], ddof=1))
