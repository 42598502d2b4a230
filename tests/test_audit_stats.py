"""Leaf-tuple audit statistics against hand-computed values and the shuffle null."""
import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from common.audit.config import AuditConfig
from common.audit.leaf_stats import association, audit_markdown, leaf_audit, nmi, progress_bins, purity


def test_purity_and_nmi_hand_computed():
    # contingency rows (clusters) x cols (bins): [[2, 1], [0, 3]]
    u = np.array([0, 0, 0, 1, 1, 1])
    v = np.array([0, 0, 1, 1, 1, 1])
    assert purity(u, v) == pytest.approx(5 / 6)
    h_u = math.log(2)
    h_v = math.log(3) - (2 / 3) * math.log(2)
    mi = math.log(2) / 6 + math.log(1.5) / 2
    assert nmi(u, v) == pytest.approx(mi / (0.5 * (h_u + h_v)), rel=1e-12)


def test_joint_tuples_are_labels_and_beat_single_leaves():
    # each carrier alone is ambiguous about the bin; the pair identifies it exactly
    l1 = np.array([0, 0, 1, 1] * 5)
    l2 = np.array([0, 1, 0, 1] * 5)
    bins = np.array([0, 1, 2, 3] * 5)
    assert purity(l1, bins) == pytest.approx(0.5)
    assert purity(np.stack([l1, l2], 1), bins) == 1.0
    assert nmi(np.stack([l1, l2], 1), bins) == pytest.approx(1.0)
    # I(l1; bins) = ln 2, H(l1) = ln 2, H(bins) = ln 4 -> NMI = ln2 / ((ln2 + 2 ln2)/2) = 2/3
    assert nmi(l1, bins) == pytest.approx(2 / 3)


def test_nmi_edge_cases():
    assert nmi(np.zeros(5), np.zeros(5)) == 1.0          # both constant
    assert nmi(np.zeros(6), np.arange(6) % 2) == 0.0     # one constant
    assert purity(np.zeros(6), np.array([0, 0, 0, 0, 1, 1])) == pytest.approx(4 / 6)
    with pytest.raises(ValueError):
        nmi(np.zeros(3), np.zeros(4))
    with pytest.raises(ValueError):
        progress_bins(np.array([0.1, np.nan]), 10)


@settings(max_examples=40, deadline=None)
@given(st.lists(st.tuples(st.integers(0, 4), st.integers(0, 5)), min_size=1, max_size=60),
       st.permutations(list(range(6))))
def test_nmi_symmetric_bounded_and_relabel_invariant(pairs, perm):
    u = np.array([p[0] for p in pairs])
    v = np.array([p[1] for p in pairs])
    value = nmi(u, v)
    assert -1e-12 <= value <= 1 + 1e-12
    assert value == pytest.approx(nmi(v, u), abs=1e-12)
    assert value == pytest.approx(nmi(u, np.array(perm)[v]), abs=1e-12)
    assert 1 / len(set(v.tolist())) - 1e-12 <= purity(u, v) <= 1.0


def test_progress_bins_edges():
    assert progress_bins(np.array([0.0, 0.0999, 0.1, 0.95, 1.0, 1.2]), 10).tolist() == [0, 0, 1, 9, 9, 9]


def test_shuffle_z_near_zero_on_independent_labels():
    rng = np.random.default_rng(1)
    zs = []
    for seed in range(3):
        leaves = rng.integers(0, 8, size=1500)
        bins = rng.integers(0, 10, size=1500)
        r = association(leaves, bins, shuffles=60, rng=np.random.default_rng(seed))
        zs += [r["z_nmi"], r["z_purity"]]
    assert all(abs(z) < 3 for z in zs), zs


def test_shuffle_z_large_on_dependent_labels():
    rng = np.random.default_rng(2)
    progress = rng.uniform(0, 1, size=1500)
    leaves = np.minimum((progress * 5).astype(int), 4)       # one leaf per two progress bins
    noisy = np.where(rng.uniform(size=1500) < 0.3, rng.integers(0, 5, size=1500), leaves)
    r = association(noisy, progress_bins(progress, 10), shuffles=60, rng=np.random.default_rng(0))
    assert r["z_nmi"] > 20 and r["z_purity"] > 20
    assert r["nmi"] > r["null_nmi_mean"] + 0.1


def test_leaf_audit_table_means_over_carriers():
    rng = np.random.default_rng(3)
    progress = rng.uniform(0, 1, size=800)
    bins = progress_bins(progress, 10)
    leaves = np.stack([bins // 2, bins % 2, rng.integers(0, 4, size=800)], axis=1)
    cfg = AuditConfig(shuffles=20)
    res = leaf_audit(leaves, progress, cfg)
    per = res["individual_per_carrier"]
    assert res["individual_mean"]["purity"] == pytest.approx(np.mean([purity(leaves[:, i], bins) for i in range(3)]))
    assert [p["n_clusters"] for p in per] == [5, 2, 4]
    assert res["joint"]["purity"] == 1.0  # (bins // 2, bins % 2, noise) pins the bin down
    assert res["joint"]["purity"] > res["individual_mean"]["purity"]
    assert res["joint"]["nmi"] == pytest.approx(nmi(leaves, bins))
    table = audit_markdown(res)
    assert "Joint tuple" in table and "Individual leaf" in table
