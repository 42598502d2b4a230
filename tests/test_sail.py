"""SAIL map (Eq. sail_projection) against independent references: the same objective solved
as an exact slack QP by quadprog, the closed-form Jacobian (Eq. sail_jacobian), and the
exact constrained projection (quadprog) for large kappa."""
import numpy as np
import pytest
import quadprog
import torch
from hypothesis import HealthCheck, assume, given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from common.policy.sail import (
    SailConfig,
    absorb_fixed,
    normalize_rows,
    sail_implicit_step_np,
    sail_project,
    sail_project_np,
    sail_rows_np,
)

D = 9
FAST = settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.too_slow])
coords = st.floats(-2.0, 2.0, allow_nan=False, allow_infinity=False)


def _unit_rows(C):
    return C / np.linalg.norm(C, axis=-1, keepdims=True)


def _reference(a, C, c, kappa, free=None):
    """Independent solve of the SAIL objective as an exact QP in (x, s) with quadprog:

        min 1/2||x - a||^2 + kappa/2 ||s||^2   s.t.  C x + s >= c,

    (for fixed x the optimal slack is s = [c - C x]_+, so the x-part is the SAIL minimizer).
    `free` keeps the other coordinates of x at a; the reduced rows are normalized here."""
    free = np.ones(D, bool) if free is None else free
    c = c - C[:, ~free] @ a[~free]  # fixed coordinates move to the right-hand side
    Cf = C[:, free]
    norm = np.linalg.norm(Cf, axis=1)
    keep = norm > 1e-9
    Cn, cn = Cf[keep] / norm[keep, None], c[keep] / norm[keep]
    m, nf = len(cn), int(free.sum())
    if m == 0 or kappa == 0:
        return a.copy()
    G = np.diag(np.concatenate([np.ones(nf), np.full(m, kappa)]))
    q = np.concatenate([a[free], np.zeros(m)])
    A = np.hstack([Cn, np.eye(m)])
    b = cn
    z = quadprog.solve_qp(G, q, A.T.copy(), b, 0)[0]
    x = a.copy()
    x[free] = z[:nf]
    return x


def _problem(draw_rows):
    a, C, c, zero = draw_rows
    C = C * (~zero)[:, None]  # some zero rows, which SAIL must ignore
    return a, C, c


rows_strategy = st.integers(1, 12).flatmap(
    lambda m: st.tuples(
        hnp.arrays(np.float64, D, elements=st.floats(-1, 1)),
        hnp.arrays(np.float64, (m, D), elements=coords),
        hnp.arrays(np.float64, m, elements=coords),
        hnp.arrays(bool, m),
    )
)


@FAST
@given(rows_strategy, st.sampled_from([0.5, 3.0, 20.0, 100.0]))
def test_minimizer_matches_slack_qp_reference(rows, kappa):
    a, C, c = _problem(rows)
    mask = np.ones(len(c), bool)
    ref = _reference(a, C, c, kappa)
    x_np = sail_project_np(a[None], C[None], c[None], mask[None], kappa)[0]
    np.testing.assert_allclose(x_np, ref, atol=1e-6)
    x_t = sail_project(torch.from_numpy(a[None]), torch.from_numpy(C[None]), torch.from_numpy(c[None]),
                       torch.from_numpy(mask[None]), kappa)[0].numpy()
    np.testing.assert_allclose(x_t, ref, atol=1e-6)


def test_batched_full_size_problems_match_reference_and_torch():
    """B=16, M=34 (the env's row budget) with masked and zero rows, per-sample kappa."""
    rng = np.random.default_rng(7)
    B, M = 16, 34
    a = rng.uniform(-1, 1, (B, D))
    C = rng.normal(size=(B, M, D)) * (rng.random((B, M, 1)) < 0.8)
    C[:, :3] *= 1e3  # row units must not matter
    c = rng.normal(size=(B, M)) * np.linalg.norm(C, axis=-1)
    mask = rng.random((B, M)) < 0.8
    kappa = rng.choice([1.0, 10.0, 50.0], B)
    x_np = sail_project_np(a, C, c, mask, kappa)
    x_t = sail_project(torch.from_numpy(a), torch.from_numpy(C), torch.from_numpy(c), torch.from_numpy(mask),
                       torch.from_numpy(kappa)).numpy()
    np.testing.assert_allclose(x_t, x_np, atol=1e-9)
    for b in range(B):
        ref = _reference(a[b], C[b] * mask[b, :, None], c[b] * mask[b], kappa[b])
        np.testing.assert_allclose(x_np[b], ref, atol=1e-6)


def _active_region_problem(seed, k, kappa):
    """k well-separated violated rows; all other rows far satisfied (fixed active set)."""
    rng = np.random.default_rng(seed)
    Q, _ = np.linalg.qr(rng.normal(size=(D, D)))
    CJ = Q[:k] + 0.2 * rng.normal(size=(k, D))  # linearly independent, not orthogonal
    a = rng.uniform(-0.5, 0.5, D)
    cJ = CJ @ a + np.linalg.norm(CJ, axis=1) * rng.uniform(0.3, 1.0, k)  # violated
    Cfar = rng.normal(size=(5, D))
    cfar = Cfar @ a - 50.0 * np.linalg.norm(Cfar, axis=1)  # satisfied with a huge margin
    return a, np.vstack([CJ, Cfar]), np.concatenate([cJ, cfar]), CJ


@settings(max_examples=20, deadline=None)
@given(st.integers(0, 10_000), st.integers(1, 6), st.sampled_from([0.5, 5.0, 50.0]))
@pytest.mark.sweep
def test_jacobian_matches_sail_jacobian_in_fixed_active_set(seed, k, kappa):
    a, C, c, CJ = _active_region_problem(seed, k, kappa)
    mask = torch.ones(1, len(c), dtype=torch.bool)
    Ct, ct = torch.from_numpy(C[None]), torch.from_numpy(c[None])
    x = sail_project(torch.from_numpy(a[None]), Ct, ct, mask, kappa)[0].numpy()
    Cn, cn = _unit_rows(C), c / np.linalg.norm(C, axis=1)
    r = cn - Cn @ x
    assume(np.all(r[:k] > 1e-6) and np.all(r[k:] < -1e-6))  # same active set at the solution
    jac = torch.autograd.functional.jacobian(
        lambda z: sail_project(z[None], Ct, ct, mask, kappa)[0], torch.from_numpy(a)).numpy()
    CJn = _unit_rows(CJ)
    np.testing.assert_allclose(jac, np.linalg.inv(np.eye(D) + kappa * CJn.T @ CJn), atol=1e-5)


@pytest.mark.parametrize("kappa", [1.0, 9.0, 99.0])
def test_one_active_row_scales_normal_component(kappa):
    rng = np.random.default_rng(int(kappa))
    n = rng.normal(size=D) * 3.0  # unnormalized row: SAIL normalizes it
    a = rng.uniform(-0.5, 0.5, D)
    c = np.array([n @ a + 0.7 * np.linalg.norm(n)])
    Ct, ct, mask = torch.from_numpy(n[None, None]), torch.from_numpy(c[None]), torch.ones(1, 1, dtype=torch.bool)
    jac = torch.autograd.functional.jacobian(
        lambda z: sail_project(z[None], Ct, ct, mask, kappa)[0], torch.from_numpy(a)).numpy()
    u = n / np.linalg.norm(n)
    np.testing.assert_allclose(jac @ u, u / (1 + kappa), atol=1e-9)
    t = rng.normal(size=D)
    t -= (t @ u) * u
    np.testing.assert_allclose(jac @ t, t, atol=1e-9)
    # and the value: the normal residual 0.7 is shrunk to 0.7 / (1 + kappa)
    x = sail_project_np(a[None], n[None, None], c[None], np.ones((1, 1), bool), kappa)[0]
    np.testing.assert_allclose(u @ x - c[0] / np.linalg.norm(n), -0.7 / (1 + kappa), atol=1e-12)


def _qp_projection(a, C, c):
    """Exact min 1/2||x-a||^2 s.t. C x >= c (quadprog, no box)."""
    return quadprog.solve_qp(np.eye(D), a, C.T.copy(), c, 0)[0]


@settings(max_examples=15, deadline=None)
@given(st.integers(0, 10_000), st.integers(1, 8))
def test_large_kappa_approaches_exact_projection_monotonically(seed, m):
    rng = np.random.default_rng(seed)
    C = rng.normal(size=(m, D))
    x0 = rng.uniform(-1, 1, D)
    c = C @ x0 - rng.exponential(0.2, m)  # feasible (x0 satisfies every row)
    a = x0 + rng.normal(size=D)
    proj = _qp_projection(a, C, c)
    kappas = [1.0, 10.0, 100.0, 1e3, 1e4, 1e5]
    dist = [np.linalg.norm(sail_project_np(a[None], C[None], c[None], np.ones((1, m), bool), k, n_newton=60)[0] - proj)
            for k in kappas]
    assert all(d1 <= d0 + 1e-9 for d0, d1 in zip(dist, dist[1:])), dist
    if dist[0] > 1e-9:  # some row was violated: the O(1/kappa) gap closes
        assert dist[-1] < 1e-3 * dist[0] + 1e-9


@FAST
@given(rows_strategy, st.sampled_from([0.0, 1.0, 1e3]))
def test_identity_when_no_row_is_violated(rows, kappa):
    a, C, c = _problem(rows)
    c = np.minimum(c, C @ a - 1e-3)  # every row satisfied at a
    mask = np.ones((1, len(c)), bool)
    assert np.array_equal(sail_project_np(a[None], C[None], c[None], mask, kappa)[0], a)
    at = torch.from_numpy(a[None])
    out = sail_project(at, torch.from_numpy(C[None]), torch.from_numpy(c[None]), torch.from_numpy(mask), kappa)
    assert torch.equal(out, at)


def test_masked_zero_rows_and_kappa_zero_are_identity():
    rng = np.random.default_rng(0)
    a, C, c = rng.uniform(-1, 1, (4, D)), rng.normal(size=(4, 6, D)), rng.normal(size=(4, 6)) + 5.0
    assert np.array_equal(sail_project_np(a, C, c, np.zeros((4, 6), bool), 10.0), a)
    assert np.array_equal(sail_project_np(a, np.zeros_like(C), c, np.ones((4, 6), bool), 10.0), a)
    assert np.array_equal(sail_project_np(a, C, c, np.ones((4, 6), bool), 0.0), a)


def test_normalize_rows():
    C = np.array([[[3.0, 4.0] + [0.0] * 7, [0.0] * 9, [1.0] + [0.0] * 8]])
    c = np.array([[10.0, 1.0, 2.0]])
    Cn, cn, keep = normalize_rows(C, c, np.array([[True, True, False]]))
    np.testing.assert_allclose(Cn[0, 0, :2], [0.6, 0.8])
    np.testing.assert_allclose(cn, [[2.0, 0.0, 0.0]])
    assert keep.tolist() == [[True, False, False]] and np.all(Cn[0, 1:] == 0)
    Ct, ct, kt = normalize_rows(torch.from_numpy(C), torch.from_numpy(c), torch.tensor([[True, True, False]]))
    np.testing.assert_allclose(Ct.numpy(), Cn)
    np.testing.assert_allclose(ct.numpy(), cn)
    assert kt.tolist() == keep.tolist()


def test_fixed_block_stays_put_and_robots_solve_reduced_problem():
    rng = np.random.default_rng(3)
    B, M = 5, 10
    a, C = rng.uniform(-1, 1, (B, D)), rng.normal(size=(B, M, D))
    c = np.einsum("bmd,bd->bm", C, a) + rng.normal(0.0, 0.5, (B, M))
    fixed = np.zeros(D, bool)
    fixed[3:6] = True
    human = rng.uniform(-1, 1, (B, D))
    x = sail_project_np(a, C, c, np.ones((B, M), bool), 20.0, fixed_mask=fixed, fixed_action=human)
    assert np.array_equal(x[:, fixed], human[:, fixed])
    for b in range(B):
        ref = _reference(np.where(fixed, human[b], a[b]), C[b], c[b], 20.0, free=~fixed)
        np.testing.assert_allclose(x[b], ref, atol=1e-6)
    Cr, cr = absorb_fixed(C, c, fixed, human)
    assert np.all(Cr[:, :, fixed] == 0)
    np.testing.assert_allclose(cr, c - np.einsum("bmd,bd->bm", C[:, :, fixed], human[:, fixed]))
    xt = sail_project(torch.from_numpy(a), torch.from_numpy(C), torch.from_numpy(c), torch.ones(B, M, dtype=torch.bool),
                      20.0, fixed_mask=torch.from_numpy(fixed), fixed_action=torch.from_numpy(human))
    np.testing.assert_allclose(xt.numpy(), x, atol=1e-9)


def test_damped_newton_is_monotone():
    """The objective never increases along the unrolled iterates (exact line-search damping)."""
    rng = np.random.default_rng(11)
    B, M, kappa = 64, 34, 300.0
    a, C, c = rng.uniform(-1, 1, (B, D)), rng.normal(size=(B, M, D)), rng.normal(size=(B, M))
    mask = np.ones((B, M), bool)
    Cn, cn, _ = normalize_rows(C, c, mask)

    def f(x):
        r = np.maximum(cn - np.einsum("bmd,bd->bm", Cn, x), 0)
        return 0.5 * np.sum((x - a) ** 2, 1) + 0.5 * kappa * np.sum(r * r, 1)

    values = [f(sail_project_np(a, C, c, mask, kappa, n_newton=k)) for k in range(0, 25)]
    for v0, v1 in zip(values, values[1:]):
        assert np.all(v1 <= v0 + 1e-9 * np.abs(v0))
    assert np.all(values[-1] < values[0]) and np.allclose(values[-1], values[-2], rtol=1e-12)
    # plain full Newton steps are not guaranteed to be monotone on this piecewise quadratic
    full = [f(sail_project_np(a, C, c, mask, kappa, n_newton=k, damping="none")) for k in range(0, 4)]
    assert any(np.any(v1 > v0 * (1 + 1e-9)) for v0, v1 in zip(full, full[1:]))


def test_bad_inputs():
    a, C, c, m = np.zeros((2, D)), np.zeros((2, 3, D)), np.zeros((2, 3)), np.ones((2, 3), bool)
    with pytest.raises(ValueError, match="C must be"):
        sail_project_np(a, C[:, :, :8], c, m, 1.0)
    with pytest.raises(ValueError, match="NaN"):
        sail_project_np(a, C, np.full((2, 3), np.nan), m, 1.0)
    with pytest.raises(ValueError, match="kappa"):
        sail_project_np(a, C, c, m, -1.0)
    with pytest.raises(ValueError, match="mask must be bool"):
        sail_project_np(a, C, c, m.astype(int), 1.0)
    with pytest.raises(ValueError, match="damping"):
        sail_project(torch.zeros(2, D), torch.zeros(2, 3, D), torch.zeros(2, 3), torch.ones(2, 3, dtype=torch.bool), 1.0,
                     damping="bogus")
    assert SailConfig().n_newton > 0


@pytest.mark.parametrize("kappa", [10.0, 100.0])
def test_default_step_count_converges_on_full_size_rows(kappa):
    """Stationarity certificate ||grad f(a_bar)|| (strong convexity: >= distance to the
    minimizer) with the default n_newton on 256 harsh problems: 34 rows, ~half violated."""
    rng = np.random.default_rng(int(kappa))
    B, M = 256, 34
    a, C = rng.uniform(-1, 1, (B, D)), rng.normal(size=(B, M, D)) * (rng.random((B, M, 1)) < 0.7)
    c, mask = rng.normal(size=(B, M)), rng.random((B, M)) < 0.9
    x = sail_project_np(a, C, c, mask, kappa)
    norm = np.linalg.norm(C, axis=-1, keepdims=True)
    Cn = np.where(mask[..., None] & (norm > 0), C / np.where(norm > 0, norm, 1), 0)
    cn = np.where(mask, c / np.where(norm[..., 0] > 0, norm[..., 0], 1), 0)
    r = np.maximum(cn - np.einsum("bmd,bd->bm", Cn, x), 0)
    grad = (x - a) - kappa * np.einsum("bm,bmd->bd", r, Cn)
    assert np.max(np.linalg.norm(grad, axis=1)) < 1e-8
    assert np.mean(np.any(r > 0, axis=1)) > 0.9  # the problems do have active rows


@settings(max_examples=5, deadline=None)
@given(st.integers(0, 10_000), st.sampled_from([2.0, 30.0]))
def test_unrolled_gradients_match_finite_differences(seed, kappa):
    """Away from active-set switching surfaces the converged unrolled map is smooth: its torch
    autograd Jacobian w.r.t. a_ST, C and c equals central differences of the numpy twin."""
    rng = np.random.default_rng(seed)
    M = 6
    a = rng.uniform(-1, 1, (1, D))
    C = rng.normal(size=(1, M, D))
    c = np.einsum("bmd,bd->bm", C, a) + rng.normal(0.0, 1.0, (1, M))
    mask = np.ones((1, M), bool)
    x = sail_project_np(a, C, c, mask, kappa)
    Cn, cn = C / np.linalg.norm(C, axis=-1, keepdims=True), c / np.linalg.norm(C, axis=-1)
    assume(np.min(np.abs(cn - np.einsum("bmd,bd->bm", Cn, x))) > 1e-3)
    jac = torch.autograd.functional.jacobian(
        lambda a_, C_, c_: sail_project(a_, C_, c_, torch.from_numpy(mask), kappa),
        tuple(torch.from_numpy(v) for v in (a, C, c)))
    eps = 1e-6
    for k, v in enumerate((a, C, c)):
        for i in range(v.size):
            args_p, args_m = [a, C, c], [a, C, c]
            args_p[k], args_m[k] = v.copy(), v.copy()
            args_p[k].flat[i] += eps
            args_m[k].flat[i] -= eps
            fd = (sail_project_np(*args_p, mask, kappa) - sail_project_np(*args_m, mask, kappa)) / (2 * eps)
            np.testing.assert_allclose(jac[k].numpy().reshape(D, -1)[:, i], fd.ravel(), atol=1e-6)


def test_prepared_rows_give_the_same_implicit_step():
    """The learner prepares a batch's rows once (``sail_rows_np``) and reuses them at every
    solve: the same bits as preparing them at each solve, human blocks included; a bad a_ST
    or kappa is still refused."""
    rng = np.random.default_rng(11)
    B, M = 32, 34
    a = rng.uniform(-1.2, 1.2, (B, D))
    C = rng.normal(size=(B, M, D)) * (rng.random((B, M, 1)) < 0.8)
    c = rng.normal(size=(B, M))
    mask = rng.random((B, M)) < 0.8
    fixed = np.repeat(rng.random((B, D // 3)) < 0.3, 3, axis=1)
    human = rng.uniform(-1, 1, (B, D))
    rows = sail_rows_np(C, c, mask, fixed, human)
    for kappa in (0.5, 20.0):
        want = sail_implicit_step_np(a, C, c, mask, kappa, fixed, human)
        got = sail_implicit_step_np(a, C, c, mask, kappa, fixed, human, rows=rows)
        for x, y in zip(got, want):
            assert np.array_equal(x, y)
    bad = a.copy()
    bad[3, 1] = np.nan
    with pytest.raises(ValueError, match="a_st"):
        sail_implicit_step_np(bad, C, c, mask, 1.0, fixed, human, rows=rows)
    with pytest.raises(ValueError, match="kappa"):
        sail_implicit_step_np(a, C, c, mask, -1.0, fixed, human, rows=rows)
