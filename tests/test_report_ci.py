"""`sage report` statistics: percentile bootstrap CIs of run means and paired differences,
against exact enumeration and a direct resampling loop with the same RNG."""
import itertools
import json

import numpy as np
import pytest

from sage.report import (BOOTSTRAP_RESAMPLES, BOOTSTRAP_SEED, EVAL_KEYS, Result, bootstrap_ci, load_results,
                         paired_difference, summarize, table_markdown)


def _exact_percentile_interval(values, level=0.95):
    """The percentile bootstrap interval of the ideal bootstrap: enumerate all n^n equally
    likely resamples, take the (1-level)/2 and (1+level)/2 quantiles of their means (the
    smallest mean whose CDF reaches the level)."""
    n = len(values)
    means = sorted(np.mean([values[i] for i in idx]) for idx in itertools.product(range(n), repeat=n))
    cdf = np.arange(1, len(means) + 1) / len(means)
    tail = (1 - level) / 2
    return means[int(np.argmax(cdf >= tail))], means[int(np.argmax(cdf >= 1 - tail))]


def test_percentile_interval_matches_exact_enumeration():
    # mean of 4 resampled values from (0, 0, 0, 1) is K/4 with K ~ Binomial(4, 1/4):
    # CDF 0.316, 0.738, 0.949, 0.996, 1 -> 2.5% quantile 0, 97.5% quantile 3/4
    values = [0.0, 0.0, 0.0, 1.0]
    assert _exact_percentile_interval(values) == (0.0, 0.75)
    lo, hi = bootstrap_ci(values)
    assert (lo, hi) == (0.0, 0.75)
    # three runs: 27 resamples, the extremes each have probability 1/27 > 2.5%
    assert bootstrap_ci([0.6, 0.8, 0.4]) == pytest.approx([0.4, 0.8])
    assert _exact_percentile_interval([0.6, 0.8, 0.4]) == pytest.approx((0.4, 0.8))


def test_bootstrap_equals_a_direct_resampling_loop():
    values = [0.31, 0.95, 0.12, 0.5, 0.77, 0.0, 0.64]
    rng = np.random.default_rng(BOOTSTRAP_SEED)
    n = len(values)
    means = []
    for _ in range(BOOTSTRAP_RESAMPLES):
        means.append(sum(values[rng.integers(0, n)] for _ in range(n)) / n)
    expected = np.percentile(means, [2.5, 97.5])
    np.testing.assert_allclose(bootstrap_ci(values), expected, rtol=0, atol=1e-12)
    # None/NaN runs are dropped before resampling
    np.testing.assert_allclose(bootstrap_ci(values + [None, float("nan")]), expected, rtol=0, atol=1e-12)


def test_stratified_bootstrap_equals_a_direct_loop():
    """Family cells: the mean of scenario means, seeds resampled within each scenario."""
    values = [0.2, 0.4, 0.9, 1.0, 0.5, 0.7]
    strata = ["b", "b", "a", "a", "a", "b"]
    groups = {"a": [0.9, 1.0, 0.5], "b": [0.2, 0.4, 0.7]}
    rng = np.random.default_rng(BOOTSTRAP_SEED)
    stat = np.zeros(BOOTSTRAP_RESAMPLES)
    for label in sorted(groups):
        g = groups[label]
        for b in range(BOOTSTRAP_RESAMPLES):
            stat[b] += np.mean([g[rng.integers(0, len(g))] for _ in g])
    expected = np.percentile(stat / 2, [2.5, 97.5])
    np.testing.assert_allclose(bootstrap_ci(values, strata=strata), expected, rtol=0, atol=1e-12)


def test_degenerate_samples_give_no_interval():
    assert all(np.isnan(bootstrap_ci([])))
    assert all(np.isnan(bootstrap_ci([0.7])))
    assert all(np.isnan(bootstrap_ci([0.7, None])))
    # a family with a one-run scenario: no interval (that scenario has no spread to resample)
    assert all(np.isnan(bootstrap_ci([0.1, 0.2, 0.3], strata=["a", "a", "b"])))
    assert bootstrap_ci([0.5, 0.5, 0.5]) == [0.5, 0.5]


def _r(method, scenario, seed, **ev):
    e = {k: 0.5 for k in EVAL_KEYS}
    e.update(ev)
    return Result(method, scenario, seed, e, [], {})


def test_paired_difference_matches_runs_on_scenario_and_seed():
    ref = [_r("happo", "maze", s, col_per_1k=c) for s, c in enumerate((10.0, 20.0, 30.0))]
    new = [_r("happo_cbf", "maze", s, col_per_1k=c) for s, c in enumerate((1.0, 2.0, 3.0))]
    extra = [_r("happo", "chicane", 0, col_per_1k=1000.0),        # no partner: not paired
             _r("happo_cbf", "maze", 7, col_per_1k=0.0)]
    p = paired_difference(ref + new + extra, "happo", "happo_cbf", "col_per_1k")
    assert p["n"] == 3
    assert p["from"] == pytest.approx(20.0) and p["to"] == pytest.approx(2.0)
    assert p["diff"] == pytest.approx(-18.0) and p["reduction_pct"] == pytest.approx(90.0)
    # the paired differences (-9, -18, -27): a direct loop over the same resample indices
    d = np.array([-9.0, -18.0, -27.0])
    rng = np.random.default_rng(BOOTSTRAP_SEED)
    idx = np.array([[rng.integers(0, 3) for _ in range(3)] for _ in range(BOOTSTRAP_RESAMPLES)])
    np.testing.assert_allclose(p["ci"], np.percentile(d[idx].mean(1), [2.5, 97.5]), atol=1e-12)
    assert p["ci"] == pytest.approx([-27.0, -9.0])      # extremes: 1/27 each
    # new = ref / 10 in every pair: every resample's reduction is exactly 90%
    assert p["reduction_pct_ci"] == pytest.approx([90.0, 90.0])
    # a constant paired difference has a zero-width interval; no reduction asked for
    q = paired_difference([_r("a", "maze", s, success_rate=v) for s, v in enumerate((0.2, 0.5))]
                          + [_r("b", "maze", s, success_rate=v + 0.1) for s, v in enumerate((0.2, 0.5))],
                          "a", "b", "success_rate", relative=False)
    assert q["ci"] == pytest.approx([0.1, 0.1]) and "reduction_pct" not in q


def test_paired_difference_without_pairs_or_with_one_pair():
    p = paired_difference([_r("happo", "maze", 0), _r("happo_cbf", "maze", 1)], "happo", "happo_cbf", "col_per_1k")
    assert p["n"] == 0 and np.isnan(p["diff"]) and all(np.isnan(p["ci"]))
    p = paired_difference([_r("happo", "maze", 0, col_per_1k=0.0), _r("happo_cbf", "maze", 0, col_per_1k=1.0)],
                          "happo", "happo_cbf", "col_per_1k")
    assert p["n"] == 1 and p["diff"] == 1.0 and all(np.isnan(p["ci"])) and p["reduction_pct"] is None


def _write(tmp_path, method, scenario, seed, sr, col, viol=0.5):
    ev = {k: 0.5 for k in EVAL_KEYS}
    ev.update(success_rate=sr, col_per_1k=col, proposal_violation=viol)
    curve = [{"progress": p, "w_gap": 1.0, "cos_ind_team": 0.9, "env_steps": 1000 * (i + 1), "episodes": 1,
              "ep_collision_steps_mean": col, "ep_drop_mean": 0.0} for i, p in enumerate((0.0, 1.0))]
    path = tmp_path / f"{method}__{scenario}__{seed}.json"
    path.write_text(json.dumps({"method": method, "scenario": scenario, "seed": seed, "eval": ev,
                                "budget": {}, "train_curve": curve}))
    return path


def test_summary_and_table_carry_the_intervals(tmp_path):
    paths = []
    for seed, (sr0, sr1) in enumerate(((0.6, 0.5), (0.8, 0.7), (0.4, 0.4))):
        paths += [_write(tmp_path, "happo", "maze", seed, sr0, 40.0 + seed),
                  _write(tmp_path, "happo_cbf", "maze", seed, sr1, 1.0)]
    s = summarize(load_results(paths))
    assert s["bootstrap"] == {"method": "percentile", "level": 0.95, "resamples": 10_000, "seed": 0,
                              "unit": "runs (pairs matched on (scenario, seed) for differences)"}
    assert s["overall"]["happo"]["success_rate"]["ci"] == pytest.approx([0.4, 0.8])
    assert s["scenarios"]["maze"]["happo"]["ci"]["success_rate"] == pytest.approx([0.4, 0.8])
    assert s["families"]["CCN"]["happo"]["ci"]["success_rate"] == pytest.approx([0.4, 0.8])
    sh = s["headline"]["shield"]
    # SR cost of the shield, paired: differences (-0.1, -0.1, 0.0)
    assert sh["success_rate"]["paired"]["n"] == 3
    assert sh["success_rate"]["paired"]["diff"] == pytest.approx(-0.2 / 3)
    assert sh["success_rate"]["paired"]["ci"] == pytest.approx([-0.1, 0.0])
    assert sh["col_per_1k"]["paired"]["ci"] == pytest.approx([-41.0, -39.0])
    md = table_markdown(s)
    assert "| Maze | 60.0 [40.0, 80.0] | 41.0 [40.0, 42.0] |" in md
    assert "| HAPPO | 3 | 60.0 ± 16.3 [40.0, 80.0] |" in md
    assert "paired over 3 matched (scenario, seed) runs" in md
    assert "SR Δ -6.7 pp [-10.0, 0.0]" in md
    assert "Col./1k Δ -40.00 [-41.00, -39.00] (reduction 97.6% [97.5, 97.6])" in md
    assert "10,000 resamples" in md
    json.dumps(s, allow_nan=True)   # summary.json stays serializable
