"""Hypothesis properties of the joint CBF-QP shield, Eq. (qpshield)."""
import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from common.shield.qp import BACKENDS, STATUS_INFEASIBLE, STATUS_OPTIMAL, qp_violation, solve_cbf_qp

D = 9
unit_floats = st.floats(-1.0, 1.0, allow_nan=False, allow_subnormal=False)


@st.composite
def feasible_problem(draw, max_rows=12):
    """Rows that a safe action x0 in the box satisfies with a Slater margin; proposal
    anywhere near the box. Without the margin, a row whose free part is ~1e-9 next to
    an O(1) human block can pin the feasible set to a single point that rounding
    empties (then the shield fails closed; see the regression test below). Exactly
    degenerate vertices are covered by the degenerate families of test_qp.py."""
    M = draw(st.integers(1, max_rows))
    x0 = draw(arrays(np.float64, D, elements=st.floats(-0.9, 0.9)))
    C = draw(arrays(np.float64, (M, D), elements=unit_floats))
    margin = draw(arrays(np.float64, M, elements=st.floats(1e-6, 0.5)))
    a = draw(arrays(np.float64, D, elements=st.floats(-1.3, 1.3)))
    mask = draw(arrays(np.bool_, M))
    fixed = draw(arrays(np.bool_, D)) if draw(st.booleans()) else np.zeros(D, bool)
    a = np.where(fixed, x0, a)  # a fixed (human) block consistent with x0 keeps the set nonempty
    return a[None], C[None], (C @ x0 - margin)[None], mask[None], fixed[None]


def test_feasible_set_pinned_to_a_point_below_rounding_fails_closed():
    """Hypothesis found this: a1 is pinned to 0.5 by a row whose only free coefficient
    is ~1e-9 against a1 <= 0.5; moving a1 by 0.5 to clear a 5e-10 violation. Whatever
    the solver concludes, it must never call a violating answer optimal, and a
    fail-closed answer reports the violation it leaves (here the slack QP keeps it:
    rho * 5e-10**2 is far cheaper than the 0.5 move)."""
    t = 9.90442294e-10
    x0 = np.full(D, 0.5)
    C = np.full((1, 2, D), t)
    C[0, 0, 1], C[0, 1, 0] = -1.0, 1.0
    c = np.einsum("bmd,d->bm", C, x0)                   # both rows active at x0 (no margin)
    a = x0.copy()[None]
    a[0, 1] = 0.0
    fixed = np.ones((1, D), bool)
    fixed[0, 1] = False
    r = solve_cbf_qp(a, C, c, np.ones((1, 2), bool), fixed)
    assert (r.a_exec[fixed] == a[fixed]).all() and np.abs(r.a_exec).max() <= 1.0
    if r.status[0] == STATUS_OPTIMAL:
        assert qp_violation(r.a_exec, C, c)[0] <= 1e-8
    else:
        assert r.status[0] == STATUS_INFEASIBLE
        assert abs(r.slack[0] - qp_violation(r.a_exec, C, c)[0]) <= 1e-12 and r.slack[0] <= 1e-8


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
