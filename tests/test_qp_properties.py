"""Hypothesis properties of the joint CBF-QP shield, Eq. (qpshield)."""
import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from common.qp import BACKENDS, STATUS_INFEASIBLE, STATUS_OPTIMAL, qp_violation, solve_cbf_qp

D = 9
unit_floats = st.floats(-1.0, 1.0, allow_nan=False, allow_subnormal=False)


@st.composite
def feasible_problem(draw, max_rows=12):
    """Rows that a safe action x0 in the box satisfies; proposal anywhere near the box."""
    M = draw(st.integers(1, max_rows))
    x0 = draw(arrays(np.float64, D, elements=st.floats(-0.9, 0.9)))
    C = draw(arrays(np.float64, (M, D), elements=unit_floats))
    margin = draw(arrays(np.float64, M, elements=st.floats(0.0, 0.5)))
    a = draw(arrays(np.float64, D, elements=st.floats(-1.3, 1.3)))
    mask = draw(arrays(np.bool_, M))
    fixed = draw(arrays(np.bool_, D)) if draw(st.booleans()) else np.zeros(D, bool)
    a = np.where(fixed, x0, a)  # a fixed (human) block consistent with x0 keeps the set nonempty
    return a[None], C[None], (C @ x0 - margin)[None], mask[None], fixed[None]


@st.composite
def infeasible_problem(draw):
    """Feasible rows plus two opposing rows with an empty intersection."""
    a, C, c, mask, fixed = draw(feasible_problem(max_rows=8))
    n = draw(arrays(np.float64, D, elements=unit_floats).filter(lambda v: np.linalg.norm(v) > 0.3))
    lo_off = draw(st.floats(-0.5, 0.5))
    gap = draw(st.floats(0.05, 0.5))
    C = np.concatenate([C, np.stack([n, -n])[None]], axis=1)
    c = np.concatenate([c, [[lo_off + gap, -lo_off]]], axis=1)  # n·x ≥ lo+gap and n·x ≤ lo
    mask = np.concatenate([mask, [[True, True]]], axis=1)
    return a, C, c, mask, np.zeros_like(fixed)


@settings(max_examples=150, deadline=None)
@given(feasible_problem(), st.sampled_from(sorted(BACKENDS)))
def test_feasible_proposal_is_returned_unchanged(prob, backend):
    a, C, c, mask, fixed = prob
    a = np.clip(a, -1.0, 1.0)
    c = np.minimum(c, np.einsum("bmd,bd->bm", C, a))  # now a itself satisfies every row
    r = solve_cbf_qp(a, C, c, mask, fixed, backend=backend)
    assert r.status[0] == STATUS_OPTIMAL
    if backend == "dual_active_set":
        np.testing.assert_array_equal(r.a_exec, a)  # exactly: no step is ever taken
    else:
        np.testing.assert_allclose(r.a_exec, a, atol=1e-7)


@settings(max_examples=200, deadline=None)
@given(feasible_problem())
def test_projection_is_feasible_idempotent_and_keeps_fixed_block(prob):
    a, C, c, mask, fixed = prob
    r = solve_cbf_qp(a, C, c, mask, fixed)
    x = r.a_exec
    assert r.status[0] == STATUS_OPTIMAL
    assert (x[fixed] == a[fixed]).all()  # bit-identical human block
    assert qp_violation(x, C, c, mask)[0] <= 1e-8
    assert (x[~fixed] >= -1.0).all() and (x[~fixed] <= 1.0).all()
    assert r.kkt_residual[0] <= 1e-6
    again = solve_cbf_qp(x, C, c, mask, fixed)
    np.testing.assert_allclose(again.a_exec, x, atol=1e-9)
    assert again.correction_norm[0] <= 1e-9


@settings(max_examples=150, deadline=None)
@given(infeasible_problem())
def test_infeasible_sets_fail_closed(prob):
    a, C, c, mask, fixed = prob
    r = solve_cbf_qp(a, C, c, mask, fixed)
    x = r.a_exec
    assert r.status[0] == STATUS_INFEASIBLE
    assert r.slack[0] > 0 and abs(r.slack[0] - qp_violation(x, C, c, mask)[0]) <= 1e-12
    assert (np.abs(x) <= 1.0).all()  # the box always holds
    # The answer has no more squared violation than the clipped proposal (a slack-QP candidate).
    s = lambda v: np.maximum(c - np.einsum("bmd,bd->bm", C, v), 0.0)[mask]  # noqa: E731
    assert (s(x) ** 2).sum() <= (s(np.clip(a, -1, 1)) ** 2).sum() + 1e-12
    # The raw proposal is returned only where it is itself the slack-QP optimum:
    # inside the box that requires Cᵀ[c − C a]_+ = 0.
    grad = C[0][mask[0]].T @ s(a)
    if (np.abs(a) < 1.0).all() and np.linalg.norm(grad) > 1e-6:
        assert np.abs(x - a).max() > 1e-9
