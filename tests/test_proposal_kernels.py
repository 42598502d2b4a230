"""The actor's proposal kernels (common/policy/proposal_kernels.py) against their
numpy references (common/policy/reference.py): the squashed-Gaussian sample and its log-density, and the
human blocks, on the same draws, with and without human carriers, and every
error the references raise."""
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from common.policy import reference
from common.policy.proposal import proposal_log_prob_np, proposal_sample_np
from common.policy.rollout import human_blocks

F32_STEP = float(np.spacing(np.float32(1.0)))   # a float32 ulp near |a| = 1, the largest there is


def _human_carrier(rng, B, N=3, rate=0.3):
    return rng.random((B, N)) < rate


def _assert_samples_match(got, want):
    """Same stored samples, or (rarely) one float32 step apart where numpy's and
    libm's tanh round differently; log-densities equal to rounding where equal."""
    (a, logp), (a_ref, logp_ref) = got, want
    same = a == a_ref
    assert np.all(np.abs(a - a_ref) <= F32_STEP)
    assert same.mean() > 0.999
    rows = same.reshape(len(a), logp.shape[1], -1).all(-1)
    np.testing.assert_allclose(logp[rows], logp_ref[rows], rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize("seed", range(4))
def test_sample_equals_reference_on_the_same_draws(seed):
    rng = np.random.default_rng(seed)
    B = 257
    center = rng.uniform(-1.6, 1.6, (B, 9))
    center[:5] = [[1.0] * 9, [-1.0] * 9, [0.999] * 9, [2.0] * 9, [0.0] * 9]   # faces, outside, middle
    log_std = rng.uniform(-2.0, 0.7, 9)
    got = proposal_sample_np(center, log_std, np.random.default_rng(seed + 10))
    want = reference.proposal_sample(center, log_std, np.random.default_rng(seed + 10))
    _assert_samples_match(got, want)
    a = got[0]
    assert np.array_equal(a, a.astype(np.float32).astype(np.float64))
    assert np.all(np.abs(a) < 1)


def test_sample_with_per_sample_log_std_and_human_carriers():
    rng = np.random.default_rng(7)
    B = 200
    center = rng.uniform(-1.2, 1.2, (B, 9))
    log_std = rng.uniform(-1.5, 0.5, (B, 9))
    human_carrier = _human_carrier(rng, B)
    human = rng.uniform(-1, 1, (B, 9))
    got = proposal_sample_np(center, log_std, np.random.default_rng(1), human_carrier=human_carrier, human_action=human)
    want = reference.proposal_sample(center, log_std, np.random.default_rng(1), human_carrier=human_carrier,
                                        human_action=human)
    _assert_samples_match(got, want)
    fixed = np.repeat(human_carrier, 3, axis=1)
    np.testing.assert_array_equal(got[0][fixed], human[fixed])
    assert np.all(got[1][human_carrier] == 0) and np.all(got[1][~human_carrier] != 0)


@settings(max_examples=60, deadline=None)
@given(st.integers(1, 40), st.floats(-3.0, 1.0), st.floats(0.0, 2.5), st.integers(0, 2**31 - 1))
def test_log_prob_equals_reference(B, log_std_level, spread, seed):
    rng = np.random.default_rng(seed)
    center = rng.uniform(-spread, spread, (B, 9))
    log_std = log_std_level + rng.uniform(-0.5, 0.5, 9)
    a = np.clip(np.tanh(rng.normal(0.0, 2.0, (B, 9))), -1 + 1e-6, 1 - 1e-6)
    np.testing.assert_allclose(proposal_log_prob_np(center, log_std, a),
                               reference.proposal_log_prob(center, log_std, a), rtol=1e-12, atol=1e-10)


def test_log_prob_of_the_kernels_sample_is_its_own():
    """The sampler's log-density and proposal_log_prob_np's are the same arithmetic."""
    rng = np.random.default_rng(3)
    center = rng.uniform(-1.5, 1.5, (500, 9))
    log_std = rng.uniform(-1, 0.3, 9)
    a, logp = proposal_sample_np(center, log_std, rng)
    np.testing.assert_array_equal(logp, proposal_log_prob_np(center, log_std, a))


def test_log_prob_nan_center_propagates_like_the_reference():
    center = np.zeros((2, 9))
    center[1, 4] = np.nan
    a = np.full((2, 9), 0.2)
    got, want = proposal_log_prob_np(center, np.zeros(9), a), reference.proposal_log_prob(center, np.zeros(9), a)
    np.testing.assert_array_equal(np.isnan(got), np.isnan(want))
    assert np.isnan(got[1, 1]) and np.isfinite(got[0]).all()


@pytest.mark.parametrize("bad", [1.0, -1.0, np.nan, np.inf, 1.5])
def test_log_prob_refuses_outside_the_box_like_the_reference(bad):
    a = np.zeros((3, 9))
    a[2, 7] = bad
    for fn in (proposal_log_prob_np, reference.proposal_log_prob):
        with pytest.raises(ValueError, match=r"\|a\| < 1"):
            fn(np.zeros((3, 9)), np.zeros(9), a)


@pytest.mark.parametrize("where", ["center", "log_std"])
def test_sample_refuses_nonfinite_inputs_like_the_reference(where):
    center, log_std = np.zeros((4, 9)), np.zeros(9)
    (center[3] if where == "center" else log_std)[5] = np.nan
    for fn in (proposal_sample_np, reference.proposal_sample):
        with pytest.raises(ValueError, match="finite"):
            fn(center, log_std, np.random.default_rng(0))


def test_a_nonfinite_center_inside_a_human_block_is_not_sampled():
    """The human's block is taken as measured; only the sampled blocks need a finite center."""
    center = np.zeros((2, 9))
    center[0, 3:6] = np.nan
    human_carrier = np.array([[False, True, False], [False, False, False]])
    human = np.full((2, 9), 0.5)
    a, logp = proposal_sample_np(center, np.zeros(9), np.random.default_rng(0), human_carrier=human_carrier,
                                 human_action=human)
    np.testing.assert_array_equal(a[0, 3:6], 0.5)
    assert logp[0, 1] == 0 and np.isfinite(logp).all()


@pytest.mark.parametrize("seed", range(3))
def test_human_blocks_equal_reference(seed):
    rng = np.random.default_rng(seed)
    B = 64
    a_tree = rng.uniform(-1, 1, (B, 9))
    human = rng.uniform(-1, 1, (B, 9))
    fixed = np.repeat(_human_carrier(rng, B), 3, axis=1)
    for f, h in ((fixed, human), (np.broadcast_to(fixed[0], (B, 9)), np.broadcast_to(human[0], (B, 9)))):
        a_st, carrier = human_blocks(a_tree, f, h, 3)
        a_ref, carrier_ref = reference.human_blocks(a_tree, f, h, 3)
        np.testing.assert_array_equal(a_st, a_ref)
        np.testing.assert_array_equal(carrier, carrier_ref)


def test_human_blocks_errors_like_the_reference():
    a_tree, human = np.zeros((4, 9)), np.zeros((4, 9))
    partial = np.zeros((4, 9), bool)
    partial[2, 3:5] = True
    bad = human.copy()
    bad[1, 6] = np.inf
    fixed = np.zeros((4, 9), bool)
    fixed[1, 6:9] = True
    for fn in (human_blocks, reference.human_blocks):
        with pytest.raises(ValueError, match="whole carrier blocks"):
            fn(a_tree, partial, human, 3)
        with pytest.raises(ValueError, match="human_action"):
            fn(a_tree, fixed, bad, 3)
        fn(a_tree, fixed, np.where(fixed, 0.0, np.nan), 3)   # NaN outside the fixed blocks is never read
