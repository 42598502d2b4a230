"""Joint CBF-QP shield, Eq. (qpshield): backends vs independent references.

References that are not our code: quadprog (Goldfarb–Idnani in Fortran) and
scipy's NNLS for KKT multipliers. The strictly convex projection has a unique
KKT point, so a KKT residual ≤ 1e-6 certifies the answer on its own.
"""
import numpy as np
import pytest
import quadprog
from scipy.optimize import nnls

from common.shield.qp import (
    BACKENDS,
    DEFAULT_BACKEND,
    STATUS_INFEASIBLE,
    STATUS_OPTIMAL,
    InvalidQPInput,
    QPConfig,
    qp_violation,
    solve_cbf_qp,
)
from common.shield.random_problems import random_cbf_problems

D = 9
TOL = 1e-6


def quadprog_project(a, C, c, mask, fixed, lo=-1.0, hi=1.0):
    """Reference: quadprog on the free variables with the substituted rows."""
    x = a.copy()
    free = ~fixed
    n = int(free.sum())
    lo, hi = np.broadcast_to(lo, a.shape)[free], np.broadcast_to(hi, a.shape)[free]
    cf = c[mask] - C[mask][:, fixed] @ a[fixed]
    Cf = C[mask][:, free]
    G = np.vstack([Cf, np.eye(n), -np.eye(n)]).T
    h = np.concatenate([cf, lo, -hi])
    x[free] = quadprog.solve_qp(np.eye(n), a[free], G, h)[0]
    return x


def kkt_check(a, x, C, c, mask, fixed, lo=-1.0, hi=1.0, act=1e-7):
    """Independent KKT residual: primal feasibility + NNLS multipliers on near-active rows."""
    free = ~fixed
    s = C[mask] @ x - c[mask]
    primal = max(0.0, -s.min(initial=np.inf), (lo - x[free]).max(), (x[free] - hi).max())
    gens = [row[free] for row, si in zip(C[mask], s) if abs(si) <= act]
    slacks = [si for si in s if abs(si) <= act]
    for k in np.flatnonzero(free):
        for sign, gap in ((1.0, x[k] - lo), (-1.0, hi - x[k])):
            if abs(gap) <= act:
                e = np.zeros(D)
                e[k] = sign
                gens.append(e[free])
                slacks.append(gap)
    g = x[free] - a[free]
    if not gens:
        return max(primal, np.abs(g).max(initial=0.0))
    A = np.array(gens).T
    lam, _ = nnls(A, g)
    stat = np.abs(A @ lam - g).max()
    comp = np.max(lam * np.abs(slacks))
    return max(primal, stat, comp)


def check_batch(a, C, c, mask, fixed, reference=True):
    """All backends agree to 1e-6, satisfy KKT to 1e-6, and match quadprog."""
    res = {name: solve_cbf_qp(a, C, c, mask, fixed, backend=name) for name in BACKENDS}
    base = res[DEFAULT_BACKEND]
    for name, r in res.items():
        assert (r.status == STATUS_OPTIMAL).all(), name
        np.testing.assert_allclose(r.a_exec, base.a_exec, atol=TOL, rtol=0, err_msg=name)
        assert r.kkt_residual.max() <= TOL, name
        np.testing.assert_array_equal(r.a_exec[fixed], a[fixed])
    for b in range(a.shape[0]):
        assert kkt_check(a[b], base.a_exec[b], C[b], c[b], mask[b], fixed[b]) <= TOL, b
        if reference:
            ref = quadprog_project(a[b], C[b], c[b], mask[b], fixed[b])
            np.testing.assert_allclose(base.a_exec[b], ref, atol=TOL, rtol=0)
    return base


@pytest.mark.sweep
def test_random_instances_match_quadprog_osqp_and_kkt():
    rng = np.random.default_rng(1)
    B = 1500
    a, C, c, x0 = random_cbf_problems(rng, B, rows=34, d=D)
    mask = rng.random((B, 34)) < 0.9
    fixed = np.zeros((B, D), dtype=bool)
    human = rng.integers(-1, 3, size=B)  # -1: no human; else carrier slot held fixed
    for b in np.flatnonzero(human >= 0):
        fixed[b, 3 * human[b]:3 * human[b] + 3] = True
        a[b, fixed[b]] = x0[b, fixed[b]]  # a measured human action consistent with x0 keeps it feasible
    base = check_batch(a, C, c, mask, fixed)
    # The instances exercise the shield: many rows violated, several active at the answer.
    assert base.active.sum(1).mean() > 3
    assert (base.correction_norm > 0).mean() > 0.9


def test_diagnostics_are_consistent():
    rng = np.random.default_rng(2)
    a, C, c, _ = random_cbf_problems(rng, 64)
    r = solve_cbf_qp(a, C, c)
    np.testing.assert_allclose(r.correction_norm, np.linalg.norm(r.a_exec - a, axis=1), atol=1e-14)
    s = np.einsum("bmd,bd->bm", C, r.a_exec) - c
    np.testing.assert_array_equal(r.active, s <= 1e-7 * np.maximum(1.0, np.linalg.norm(C, axis=2)))
    assert (r.slack == 0).all() and (r.iterations > 0).any()
    assert qp_violation(r.a_exec, C, c).max() <= 1e-9


# ---- degenerate families -------------------------------------------------------------------

def _family(rng, B, build):
    a = np.empty((B, D))
    C = np.zeros((B, 12, D))
    c = np.full((B, 12), -10.0)
    for b in range(B):
        a[b], rows, offs = build(rng)
        C[b, :len(rows)] = rows
        c[b, :len(rows)] = offs
    mask = np.abs(C).sum(2) > 0
    return a, C, c, mask


def _unit(rng):
    v = rng.normal(size=D)
    return v / np.linalg.norm(v)


def test_duplicate_and_scaled_rows():
    def build(rng):
        a = rng.uniform(-1, 1, D)
        n1, n2 = _unit(rng), _unit(rng)
        rows = [n1, n1, 2.0 * n1, n2, n2]
        offs = [n1 @ a + 0.3, n1 @ a + 0.3, 2 * (n1 @ a + 0.2), n2 @ a + 0.1, n2 @ a + 0.15]
        return a * 0.5, np.array(rows), np.array(offs) * 0.5
    rng = np.random.default_rng(3)
    a, C, c, mask = _family(rng, 100, build)
    check_batch(a, C, c, mask, np.zeros((100, D), bool))


def test_nearly_parallel_rows():
    def build(rng):
        a = rng.uniform(-0.5, 0.5, D)
        n1, w = _unit(rng), _unit(rng)
        w -= (w @ n1) * n1
        w /= np.linalg.norm(w)
        n2 = np.cos(1e-7) * n1 + np.sin(1e-7) * w  # 1e-7 rad apart
        b1 = n1 @ a + rng.uniform(0.05, 0.3)
        return a, np.array([n1, n2, -w]), np.array([b1, b1 + rng.uniform(-1e-7, 1e-7), -w @ a - 0.1])
    rng = np.random.default_rng(4)
    a, C, c, mask = _family(rng, 100, build)
    check_batch(a, C, c, mask, np.zeros((100, D), bool), reference=False)  # quadprog is unreliable here


def test_rows_active_at_the_box():
    def build(rng):
        a = rng.uniform(-1.5, 1.5, D)  # proposals partly outside the box
        k = rng.integers(D)
        x0 = rng.uniform(-0.9, 0.9, D)
        x0[k] = 1.0  # a feasible point on the box face x_k = 1
        e = np.zeros(D)
        e[k] = 1.0
        n = _unit(rng)
        b = n @ x0 - 0.05
        # A row that coincides with the box face, one more, and their (redundant) sum.
        return a, np.array([e, n, e + 0.5 * n]), np.array([1.0, b, 1.0 + 0.5 * b])
    rng = np.random.default_rng(5)
    a, C, c, mask = _family(rng, 100, build)
    res = check_batch(a, C, c, mask, np.zeros((100, D), bool), reference=False)
    # The row e_k·x ≥ 1 meets the box face x_k ≤ 1: x_k = 1 exactly and the row is reported active.
    assert (res.a_exec.max(1) >= 1 - 1e-12).all() and res.active[:, 0].all()


def test_zero_rows_and_more_active_rows_than_free_variables():
    def build(rng):
        x_star = rng.uniform(-0.5, 0.5, D)
        a = x_star + rng.uniform(-0.3, 0.3, D)
        rows = [np.zeros(D)]  # an all-zero row with c ≤ 0 is always satisfied
        offs = [-0.1]
        for _ in range(11):  # 11 rows through x_star with normals pointing away from a
            n = _unit(rng)
            if n @ (x_star - a) < 0:
                n = -n
            rows.append(n)
            offs.append(n @ x_star)
        return a, np.array(rows), np.array(offs)
    rng = np.random.default_rng(6)
    B = 80
    a, C, c, _ = _family(rng, B, build)
    mask = np.zeros((B, 12), bool)
    mask[:, :12] = True
    res = check_batch(a, C, c, mask, np.zeros((B, D), bool), reference=False)
    assert (res.active.sum(1) > D).any()  # degenerate: more rows on the boundary than variables


def test_fixed_human_block_is_substituted():
    rng = np.random.default_rng(7)
    B = 200
    a, C, c, x0 = random_cbf_problems(rng, B)
    fixed = np.zeros(D, bool)
    fixed[3:6] = True  # carrier 1 is a human partner
    a[:, fixed] = x0[:, fixed]
    a[:5, fixed] = 1.7  # a measured human action may even lie outside the robots' box
    c[:5] = np.minimum(c[:5], np.einsum("bmd,bd->bm", C[:5], np.where(fixed, a[:5], x0[:5])) - 1e-3)
    mask = np.ones((B, 34), bool)
    res = check_batch(a, C, c, mask, np.broadcast_to(fixed, (B, D)).copy())
    assert (res.a_exec[:, fixed] == a[:, fixed]).all()
    # Substitution is what the rows see: same answer as solving with c ← c − C_F a_F over the rest.
    c_sub = c - np.einsum("bmk,bk->bm", C[:, :, fixed], a[:, fixed])
    C_sub = C.copy()
    C_sub[:, :, fixed] = 0.0
    a_sub = a.copy()
    a_sub[:, fixed] = 0.0
    res2 = solve_cbf_qp(a_sub, C_sub, c_sub, mask, fixed)
    np.testing.assert_allclose(res2.a_exec[:, ~fixed], res.a_exec[:, ~fixed], atol=1e-12)


def test_general_box_bounds_per_problem():
    rng = np.random.default_rng(11)
    B = 100
    a, C, c, x0 = random_cbf_problems(rng, B, rows=20)
    lo = -rng.uniform(0.8, 1.0, (B, D))  # x0 ∈ [-0.8, 0.8] stays inside, so all stay feasible
    hi = rng.uniform(0.8, 1.0, D)
    for name in BACKENDS:
        r = solve_cbf_qp(a, C, c, lo=lo, hi=hi, backend=name)
        assert (r.status == STATUS_OPTIMAL).all() and r.kkt_residual.max() <= TOL
        assert (r.a_exec >= lo).all() and (r.a_exec <= hi).all()
        for b in range(B):
            ref = quadprog_project(a[b], C[b], c[b], np.ones(20, bool), np.zeros(D, bool), lo[b], hi)
            np.testing.assert_allclose(r.a_exec[b], ref, atol=TOL, err_msg=name)


# ---- infeasible row sets fail closed -------------------------------------------------------

def slack_qp_reference(a, C, c, rho, lo=-1.0, hi=1.0):
    """quadprog on min ½‖x−a‖² + ρ/2‖s‖² s.t. Cx + s ≥ c, s ≥ 0, box (the documented slack QP)."""
    M = len(c)
    G = np.diag(np.concatenate([np.ones(D), np.full(M, rho)]))
    A = np.block([[C, np.eye(M)], [np.zeros((M, D)), np.eye(M)],
                  [np.eye(D), np.zeros((D, M))], [-np.eye(D), np.zeros((D, M))]])
    h = np.concatenate([c, np.zeros(M), np.full(D, lo), np.full(D, -hi)])
    return quadprog.solve_qp(G, np.concatenate([a, np.zeros(M)]), A.T, h)[0][:D]


def test_infeasible_sets_return_the_slack_qp_answer():
    rng = np.random.default_rng(8)
    B = 60
    a, C, c, _ = random_cbf_problems(rng, B, rows=10)
    a *= 0.5
    for b in range(B):  # opposing rows n·x ≥ n·a + 0.3 and n·x ≤ n·a + 0.1: empty intersection
        n = _unit(rng)
        C[b, 0], c[b, 0] = n, n @ a[b] + 0.3
        C[b, 1], c[b, 1] = -n, -(n @ a[b]) - 0.1
    # Half of them also hold a row no box point can meet (x_0 ≥ 1.5).
    C[::2, 2] = 0.0
    C[::2, 2, 0] = 1.0
    c[::2, 2] = 1.5
    cfg = QPConfig()
    res = {name: solve_cbf_qp(a, C, c, backend=name) for name in BACKENDS}
    for name, r in res.items():
        assert (r.status == STATUS_INFEASIBLE).all(), name
        assert (r.slack > 0).all() and (np.abs(r.a_exec) <= 1.0).all()
        assert (np.abs(r.a_exec - a).max(1) > 1e-3).all()  # never the raw (violating) proposal
        assert r.kkt_residual.max() <= 1e-5, name
        np.testing.assert_allclose(r.slack, qp_violation(r.a_exec, C, c), atol=1e-12)
    np.testing.assert_allclose(res["osqp"].a_exec, res[DEFAULT_BACKEND].a_exec, atol=1e-5)
    for b in range(B):
        ref = slack_qp_reference(a[b], C[b], c[b], cfg.slack_rho)
        np.testing.assert_allclose(res[DEFAULT_BACKEND].a_exec[b], ref, atol=1e-6)


def test_constant_row_violated_by_the_human_block_is_infeasible():
    a = np.full((1, D), 0.2)
    C = np.zeros((1, 2, D))
    C[0, 0, 3] = 1.0  # depends only on the (fixed) human block
    C[0, 1, 0] = 1.0
    c = np.array([[0.5, 0.4]])
    fixed = np.zeros(D, bool)
    fixed[3:6] = True
    for name in BACKENDS:
        r = solve_cbf_qp(a, C, c, fixed_mask=fixed, backend=name)
        assert r.status[0] == STATUS_INFEASIBLE and r.slack[0] == pytest.approx(0.3)
        assert r.a_exec[0, 0] == pytest.approx(0.4, abs=1e-6)  # the robot rows are still met


# ---- input validation ----------------------------------------------------------------------

@pytest.mark.parametrize("arg,index", [("a_prop", (2, 4)), ("C", (1, 0, 3)), ("c", (3, 1))])
@pytest.mark.parametrize("value,kind", [(np.nan, "NaN"), (np.inf, "Inf")])
def test_nan_inf_rejected_with_argument_and_problem(arg, index, value, kind):
    rng = np.random.default_rng(9)
    a, C, c, _ = random_cbf_problems(rng, 4, rows=5)
    args = {"a_prop": a, "C": C, "c": c}
    args[arg][index] = value
    with pytest.raises(InvalidQPInput, match=rf"{arg} contains {kind}.*problem {index[0]}"):
        solve_cbf_qp(args["a_prop"], args["C"], args["c"])


def test_shape_errors_are_clear():
    rng = np.random.default_rng(10)
    a, C, c, _ = random_cbf_problems(rng, 3, rows=4)
    with pytest.raises(InvalidQPInput, match="C must be"):
        solve_cbf_qp(a, C[:, :, :8], c)
    with pytest.raises(InvalidQPInput, match="c must be"):
        solve_cbf_qp(a, C, c[:, :3])
    with pytest.raises(InvalidQPInput, match="row_mask"):
        solve_cbf_qp(a, C, c, row_mask=np.ones((3, 5), bool))
    with pytest.raises(InvalidQPInput, match="fixed_mask"):
        solve_cbf_qp(a, C, c, fixed_mask=np.ones(8, bool))
    with pytest.raises(InvalidQPInput, match="lo > hi"):
        solve_cbf_qp(a, C, c, lo=1.0, hi=-1.0)
    with pytest.raises(InvalidQPInput, match="a_prop must have 2 dims"):
        solve_cbf_qp(a[0], C, c)
    with pytest.raises(ValueError, match="unknown QP backend"):
        solve_cbf_qp(a, C, c, backend="cvx")


def test_qp_violation_hand_values():
    C = np.array([[[1.0, 0.0], [0.0, 2.0], [1.0, 1.0]]])
    c = np.array([[0.5, 1.0, 5.0]])
    a = np.array([[0.2, 0.1]])
    # violations: 0.3, 0.8, 4.7 (third masked out)
    np.testing.assert_allclose(qp_violation(a, C, c, np.array([[True, True, False]])), [0.8])
    assert qp_violation(a[0], C[0], c[0]) == pytest.approx(4.7)
    assert qp_violation(np.array([[1.0, 1.0]]), C, np.array([[0.0, 0.0, 0.0]]))[0] == 0.0


def test_edge_shapes_no_rows_empty_batch_all_fixed():
    for name in BACKENDS:
        r = solve_cbf_qp(np.full((2, D), 1.5), np.zeros((2, 0, D)), np.zeros((2, 0)), backend=name)
        np.testing.assert_array_equal(r.a_exec, np.ones((2, D)))  # only the box acts
        assert r.active.shape == (2, 0) and (r.status == STATUS_OPTIMAL).all()
        assert solve_cbf_qp(np.zeros((0, D)), np.zeros((0, 3, D)), np.zeros((0, 3)), backend=name).a_exec.shape == (0, D)
        # Everything fixed: nothing to optimize; a violated row can only be reported.
        a = np.full((2, D), 0.3)
        C = np.ones((2, 1, D))
        c = np.array([[1.0], [5.0]])  # 9·0.3 = 2.7 meets the first, not the second
        r = solve_cbf_qp(a, C, c, fixed_mask=np.ones(D, bool), backend=name)
        np.testing.assert_array_equal(r.a_exec, a)
        assert list(r.status) == [STATUS_OPTIMAL, STATUS_INFEASIBLE]
        assert r.slack[1] == pytest.approx(2.3)
