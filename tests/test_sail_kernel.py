"""The compiled SAIL Newton loop (common/policy/sail_kernels.py) against its numpy reference
``reference.sail_project`` (common/policy/reference.py).

Both see the same validated, fixed-absorbed and normalized inputs; the kernel must give the
reference's iterate (to rounding: the reference's matrix products go through BLAS) on
hypothesis-drawn arrays (small, degenerate values), on random full-size batches (up to 64
samples, 40 rows, about half violated, masked and zero rows, fixed human blocks, per-sample
kappa, both dampings, 0 / 1 / 20 steps) and on the env's own safety rows, and its result must
be as stationary as the reference's. The edge cases (kappa 0, no kept or violated row,
n_newton 0, empty batch or row set) are exact. The learner's implicit-step kernel
(``sail_implicit_step``: H^{-1} and the offset at the solution) against numpy's inverse.
"""
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from common.env.batch_env import BatchEnv
from common.env.config import EnvConfig
from common.policy import reference, sail_kernels
from common.policy.sail import SailConfig, absorb_fixed, normalize_rows, sail_implicit_step_np, sail_project_np

D = 9
HYP = settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow])
KAPPAS = [0.0, 0.5, 1.0, 10.0, 100.0, 1000.0]


def _both(*args, **kw):
    return sail_project_np(*args, **kw), reference.sail_project(*args, **kw)


def _tol(x, a):
    return 1e-9 * max(1.0, float(np.max(np.abs(a), initial=0.0)), float(np.max(np.abs(x), initial=0.0)))


def _grad_norm(x, a, C, c, mask, kappa, fixed=None, human=None):
    """||grad f(x)|| per sample of the SAIL objective of the reduced, normalized problem."""
    kappa = np.broadcast_to(np.asarray(kappa, dtype=np.float64), (len(a),))
    if fixed is not None:
        fixed = np.broadcast_to(np.asarray(fixed, dtype=bool), a.shape)
        a = np.where(fixed, human, a)
        C, c = absorb_fixed(C, c, fixed, human)
    Cn, cn, _ = normalize_rows(C, c, mask)
    r = np.maximum(cn - np.einsum("bmd,bd->bm", Cn, x), 0.0)
    return np.linalg.norm((x - a) - kappa[:, None] * np.einsum("bm,bmd->bd", r, Cn), axis=1)


def _check(a, C, c, mask, kappa, n_newton, damping, fixed=None, human=None, stationary=True):
    kw = dict(n_newton=n_newton, damping=damping, fixed_mask=fixed, fixed_action=human)
    x, ref = _both(a, C, c, mask, kappa, **kw)
    assert x.shape == ref.shape and x.dtype == np.float64
    np.testing.assert_allclose(x, ref, rtol=0, atol=_tol(ref, a))
    if fixed is not None:
        f = np.broadcast_to(fixed, a.shape)
        assert np.array_equal(x[f], np.broadcast_to(human, a.shape)[f])   # the human block stays put
    if stationary:
        gx = _grad_norm(x, a, C, c, mask, kappa, fixed, human)
        gr = _grad_norm(ref, a, C, c, mask, kappa, fixed, human)
        # the gradient's own rounding grows with |x| as well: a row of norm 2e-7 normalized
        # to unit norm puts the solution at ~1e6, where x - a is exact only to ~1e-10
        scale = (1.0 + np.max(np.abs(a)) + np.max(np.abs(np.asarray(kappa)), initial=0.0)
                 + np.max(np.abs(ref), initial=0.0))
        assert np.all(gx <= gr * (1 + 1e-6) + 1e-11 * scale), (gx.max(), gr.max())
    return x, ref


# ----------------------------------------------------------------------------- drawn arrays

coords = st.floats(-2.0, 2.0, allow_nan=False, allow_infinity=False)
arrays = st.tuples(st.integers(1, 4), st.integers(0, 12)).flatmap(
    lambda bm: st.tuples(
        hnp.arrays(np.float64, (bm[0], D), elements=st.floats(-1, 1)),
        hnp.arrays(np.float64, (bm[0], bm[1], D), elements=coords),
        hnp.arrays(np.float64, (bm[0], bm[1]), elements=coords),
        hnp.arrays(bool, (bm[0], bm[1])),           # masked rows
        hnp.arrays(bool, (bm[0], bm[1])),           # zero rows
        hnp.arrays(bool, D),                        # fixed (human) columns
        hnp.arrays(np.float64, (bm[0], D), elements=st.floats(-1, 1)),
    ))


@HYP
@given(arrays, st.sampled_from(KAPPAS), st.sampled_from([0, 1, 2, 20]), st.sampled_from(["exact", "none"]),
       st.booleans())
def test_kernel_matches_reference_on_drawn_arrays(arrs, kappa, n_newton, damping, use_fixed):
    a, C, c, mask, zero, fixed, human = arrs
    C = C * (~zero)[..., None]
    _check(a, C, c, ~mask, kappa, n_newton, damping, fixed if use_fixed else None, human if use_fixed else None,
           stationary=damping == "exact" and n_newton == 20)


# ----------------------------------------------------------------------------- random full-size batches

def _random_problem(rng, B, M):
    """B problems with M rows (row scales 1e-3..1e3), about half violated at a; some rows
    masked or zero; per-sample kappa drawn from KAPPAS."""
    a = rng.uniform(-1, 1, (B, D))
    C = rng.normal(size=(B, M, D)) * 10.0 ** rng.uniform(-3, 3, (B, M, 1))
    C *= rng.random((B, M, 1)) > 0.1                                         # zero rows
    c = np.einsum("bmd,bd->bm", C, a) + rng.normal(size=(B, M)) * np.linalg.norm(C, axis=-1)
    mask = rng.random((B, M)) < 0.85                                         # masked rows
    return a, C, c, mask


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.integers(0, 2**31), st.integers(1, 64), st.integers(1, 40), st.sampled_from(KAPPAS + ["mixed"]),
       st.sampled_from([0, 1, 20]), st.sampled_from(["exact", "none"]), st.sampled_from([None, "one", "rows"]))
def test_kernel_matches_reference_on_random_problems(seed, B, M, kappa, n_newton, damping, fixed_kind):
    rng = np.random.default_rng(seed)
    a, C, c, mask = _random_problem(rng, B, M)
    if kappa == "mixed":
        kappa = rng.choice(KAPPAS, B)
    fixed = human = None
    if fixed_kind == "one":            # one carrier's block, shared by the batch ([d])
        fixed = np.zeros(D, bool)
        fixed[3 * int(rng.integers(3)):][:3] = True
        human = rng.uniform(-1, 1, (B, D))
    elif fixed_kind == "rows":         # a per-sample block ([B,d]); some samples without one
        fixed = np.zeros((B, D), bool)
        for b in range(B):
            k = int(rng.integers(4))
            if k < 3:
                fixed[b, 3 * k:3 * k + 3] = True
        human = rng.uniform(-1, 1, (B, D))
    _check(a, C, c, mask, kappa, n_newton, damping, fixed, human,
           stationary=damping == "exact" and n_newton == 20)


@pytest.mark.parametrize("kappa", [10.0, 100.0, 1000.0])
def test_default_config_converges_like_reference(kappa):
    """The default (20 exact-damped steps) on 256 harsh problems, 34 rows, ~half violated:
    the same centers and the same stationarity as the reference."""
    rng = np.random.default_rng(int(kappa) + 1)
    a, C, c, mask = _random_problem(rng, 256, 34)
    x, ref = _check(a, C, c, mask, kappa, None, None)
    g = _grad_norm(x, a, C, c, mask, kappa)
    if kappa <= 100:
        assert g.max() < 1e-8


# ----------------------------------------------------------------------------- edge cases (exact)

def test_edge_cases_are_exact():
    rng = np.random.default_rng(0)
    B, M = 6, 8
    a, C, c = rng.uniform(-1, 1, (B, D)), rng.normal(size=(B, M, D)), rng.normal(size=(B, M)) + 3.0
    ones, zeros = np.ones((B, M), bool), np.zeros((B, M), bool)
    cases = [
        (a, C, c, ones, 0.0, 20),                   # kappa 0
        (a, C, c, zeros, 10.0, 20),                 # every row masked
        (a, np.zeros_like(C), c, ones, 10.0, 20),   # every row zero
        (a, C, c, ones, 10.0, 0),                   # no step
        (a, C, np.einsum("bmd,bd->bm", C, a) - 1.0, ones, 1e3, 20),   # no row violated
        (a, C[:, :0], c[:, :0], ones[:, :0], 10.0, 20),               # no rows at all
    ]
    for damping in ("exact", "none"):
        for args in cases:
            x, ref = _both(*args[:5], n_newton=args[5], damping=damping)
            assert np.array_equal(x, a) and np.array_equal(ref, a)
    x, ref = _both(a[:0], C[:0], c[:0], ones[:0], 10.0)   # empty batch
    assert x.shape == ref.shape == (0, D)
    # n_newton 0 with a human block: the block is replaced, nothing else moves
    fixed, human = np.zeros(D, bool), rng.uniform(-1, 1, (B, D))
    fixed[:3] = True
    x, ref = _both(a, C, c, ones, 10.0, n_newton=0, fixed_mask=fixed, fixed_action=human)
    assert np.array_equal(x, ref) and np.array_equal(x, np.where(fixed, human, a))


def test_kappa_and_inputs_broadcast_and_validate_like_reference():
    rng = np.random.default_rng(1)
    a, C, c, mask = _random_problem(rng, 8, 12)
    kappa = rng.choice(KAPPAS, 8)
    x, ref = _both(a.T.copy().T, np.asfortranarray(C), c[:, ::-1][:, ::-1], mask, kappa)   # odd layouts
    np.testing.assert_allclose(x, ref, rtol=0, atol=_tol(ref, a))
    x1, _ = _both(a, C, c, mask, 10.0)
    x2, _ = _both(a, C, c, mask, np.full(8, 10.0))
    assert np.array_equal(x1, x2)
    for bad in (dict(kappa=-1.0), dict(n_newton=-1), dict(damping="bogus")):
        kw = dict(kappa=1.0) | bad
        for fn in (sail_project_np, reference.sail_project):
            with pytest.raises(ValueError):
                fn(a, C, c, mask, **kw)


def test_kernel_releases_the_gil_and_compiles_once():
    """nogil (it runs in actor / learner threads); read-only, broadcast, strided or float32
    inputs and scalar or [B] kappa all reach the one compiled signature (no compile at run time)."""
    assert sail_kernels.sail_newton.targetoptions.get("nogil") is True
    rng = np.random.default_rng(2)
    a, C, c, mask = _random_problem(rng, 5, 7)
    sail_project_np(a, C, c, mask, 10.0)
    n_sig = len(sail_kernels.sail_newton.signatures)
    ro = a.copy()
    ro.flags.writeable = False
    fixed = np.zeros(D, bool)
    fixed[6:] = True
    for args, kw in [((ro, C, c, mask, np.full(5, 3.0)), {}),
                     ((np.broadcast_to(a[:1], a.shape), C.astype(np.float32), c[:, ::1], mask, 1), {}),
                     ((a, np.asfortranarray(C), c, mask, np.broadcast_to(2.0, (5,))),
                      dict(fixed_mask=fixed, fixed_action=ro, n_newton=3, damping="none"))]:
        x, ref = _both(*args, **kw)
        np.testing.assert_allclose(x, ref, rtol=0, atol=_tol(ref, a))
    assert len(sail_kernels.sail_newton.signatures) == n_sig


# ----------------------------------------------------------------------------- env rows

def _env_rows(name, human_slot, steps, k=8, seed=0):
    """(a_st, C, c, row_mask, fixed_mask, human_action) of a BatchEnv after each of ``steps``
    steps. Each env keeps a drift (a random constant action added to half the scripted one),
    so teams press against walls and the proposals a_st (the executed actions) violate some
    rows, as a policy's do before the shield."""
    env = BatchEnv(EnvConfig(name, human_slot=human_slot), num_envs=k, seed=seed)
    out = env.reset()
    rng = np.random.default_rng(seed)
    drift = rng.uniform(-1, 1, (k, D))
    drift[:, 2::3] *= 0.2
    for t in range(max(steps) + 1):
        act = np.clip(0.5 * env.scripted_actions() + drift + rng.normal(0.0, 0.2, (k, D)), -1.0, 1.0)
        if t in steps:
            yield act, out["C"], out["c"], out["row_mask"], out["fixed_mask"], out["human_action"]
        out = env.step(act)


@pytest.mark.parametrize("name,human_slot", [("narrow_gate", None), ("maze", 1)])
def test_kernel_matches_reference_on_env_rows(name, human_slot):
    seen_active = 0
    for a, C, c, mask, fixed, human in _env_rows(name, human_slot, steps=(0, 6, 12, 24)):
        fm = None if human_slot is None else fixed
        for kappa in (1.0, 10.0, 1000.0):
            for damping in ("exact", "none"):
                _check(a, C, c, mask, kappa, SailConfig().n_newton, damping, fm, human, stationary=damping == "exact")
        x = sail_project_np(a, C, c, mask, 10.0, fixed_mask=fm, fixed_action=human)
        seen_active += int(np.sum(np.any(x != a, axis=1)))
    assert seen_active > 0   # SAIL did move some centers on these rows


# ----------------------------------------------------------------------------- the learner's implicit step

@pytest.mark.parametrize("seed", range(3))
@pytest.mark.parametrize("kappa", [0.0, 1.0, 30.0, 1000.0])
def test_implicit_step_kernel_matches_numpy_inverse(seed, kappa):
    """At the actors' solution x*: the same x* as ``sail_project_np`` (bit for bit), H^{-1}
    and offset = x* - kappa C_J^T r_J as numpy computes them, H^{-1} H = I, and samples with
    no active row (kappa 0, masked rows) exactly H^{-1} = I, offset = x*."""
    rng = np.random.default_rng(seed)
    a, C, c, mask = _random_problem(rng, 48, 30)
    mask[:6] = False                                   # no kept row at all
    fixed = np.zeros((48, D), bool)
    fixed[::4, 3:6] = True
    human = rng.uniform(-0.5, 0.5, (48, D))
    x, H_inv, offset = sail_implicit_step_np(a, C, c, mask, kappa, fixed, human)
    assert np.array_equal(x, sail_project_np(a, C, c, mask, kappa, fixed_mask=fixed, fixed_action=human))
    H_ref, off_ref = reference.sail_implicit_step(x, C, c, mask, kappa, fixed, human)
    np.testing.assert_allclose(H_inv, H_ref, rtol=0, atol=1e-12)
    np.testing.assert_allclose(offset, off_ref, rtol=0, atol=1e-12 * max(1.0, kappa))
    assert np.array_equal(H_inv[:6], np.broadcast_to(np.eye(D), (6, D, D)))
    assert np.array_equal(offset[:6], x[:6])
    if kappa == 0.0:
        assert np.array_equal(H_inv, np.broadcast_to(np.eye(D), H_inv.shape)) and np.array_equal(offset, x)
    else:
        assert np.any(H_inv[6:] != np.eye(D))           # some rows were active


@pytest.mark.parametrize("seed", range(3))
@pytest.mark.parametrize("n_newton", [0, 1, 2, 20])
@pytest.mark.parametrize("damping", ["exact", "none"])
def test_fused_solve_and_step_equals_the_two_kernels_bit_for_bit(seed, n_newton, damping):
    """``sail_newton_implicit`` (what the learner calls) against ``sail_newton`` then
    ``sail_implicit_step`` at its answer: the same x*, H^{-1} and offset, bit for bit, on
    samples that end on an exact step (the factor reused) and samples that run out of steps
    (0 to 2 steps: recomputed), with no kept row, kappa 0 and mixed kappa."""
    rng = np.random.default_rng(10 + seed)
    a, C, c, mask = _random_problem(rng, 64, 30)
    mask[:4] = False
    kappa = rng.choice(KAPPAS, 64)
    Cn, cn, keep = normalize_rows(C, c, mask)
    args = [np.ascontiguousarray(v) for v in (a, Cn, cn, keep, kappa)]
    x, H_inv, offset = sail_kernels.sail_newton_implicit(*args, n_newton, damping == "exact", np.empty((0, D)))
    x_ref = sail_kernels.sail_newton(*args, n_newton, damping == "exact")
    H_ref, off_ref = sail_kernels.sail_implicit_step(x_ref, *args[1:])
    assert np.array_equal(x, x_ref) and np.array_equal(H_inv, H_ref) and np.array_equal(offset, off_ref)
    if n_newton == 20:
        assert np.any(H_inv[4:] != np.eye(D))           # active rows reached the factor reuse


@pytest.mark.parametrize("seed", range(3))
@pytest.mark.parametrize("n_newton", [1, 2, 20])
def test_a_warm_start_gives_the_cold_answer(seed, n_newton):
    """``sail_newton_implicit`` from x0 near the answer (the learner's warm start: the
    actors' solution at nearby a): where the warm loop converges, the cold answer to
    rounding, with the same active rows (the same H^{-1} to rounding); where it does not
    (1-2 steps), the cold loop's own iterate, bit for bit. From x0 = a exactly the cold
    loop's bits everywhere; a start at the answer itself converges on its first step."""
    rng = np.random.default_rng(20 + seed)
    a, C, c, mask = _random_problem(rng, 64, 30)
    kappa = rng.choice(KAPPAS, 64)
    Cn, cn, keep = normalize_rows(C, c, mask)
    args = [np.ascontiguousarray(v) for v in (a, Cn, cn, keep, kappa)]
    empty = np.empty((0, D))
    x_cold, H_cold, off_cold = sail_kernels.sail_newton_implicit(*args, n_newton, True, empty)
    x_full = sail_kernels.sail_newton(*args, 20, True)
    x0 = x_full + rng.normal(0.0, 1e-3, x_full.shape)
    x, H_inv, offset = sail_kernels.sail_newton_implicit(*args, n_newton, True, x0)
    cold_done = np.all(np.abs(x_cold - x_full) <= 1e-12 * (1 + np.abs(x_full)), axis=1)
    same = np.all(x == x_cold, axis=1)
    near = np.all(np.abs(x - x_full) <= 1e-12 * (1 + np.abs(x_full)), axis=1)
    assert np.all(same | near)                           # either the cold bits or the answer
    assert np.all(same[~near])                           # not converged from x0: cold's own iterate
    np.testing.assert_allclose(H_inv[cold_done & near], H_cold[cold_done & near], rtol=0, atol=1e-9)
    if n_newton == 20:
        assert np.all(near)
    for got, want in zip(sail_kernels.sail_newton_implicit(*args, n_newton, True, a.copy()),
                         (x_cold, H_cold, off_cold)):
        assert np.array_equal(got, want)
    at_answer = sail_kernels.sail_newton_implicit(*args, 1, True, x_full)[0]
    np.testing.assert_allclose(at_answer, x_full, rtol=0, atol=1e-12)


def test_a_warm_start_is_checked():
    rng = np.random.default_rng(3)
    a, C, c, mask = _random_problem(rng, 8, 5)
    fixed = np.zeros((8, D), bool)
    fixed[:, 6:] = True
    human = rng.uniform(-0.5, 0.5, (8, D))
    x, _, _ = sail_implicit_step_np(a, C, c, mask, 3.0, fixed, human)
    warm, _, _ = sail_implicit_step_np(a, C, c, mask, 3.0, fixed, human, start=x + 1e-4)
    np.testing.assert_allclose(warm, x, rtol=0, atol=1e-12)
    assert np.array_equal(warm[fixed], human[fixed])     # the human block starts and stays at the human's
    for bad in (x[:, :3], np.full_like(x, np.nan)):
        with pytest.raises(ValueError, match="start"):
            sail_implicit_step_np(a, C, c, mask, 3.0, fixed, human, start=bad)


@pytest.mark.parametrize("seed", range(4))
def test_row_preparation_kernel_matches_numpy(seed):
    """``sail_prepare`` (one compiled pass) against ``absorb_fixed`` + ``normalize_rows``:
    the same unit rows, right-hand sides, kept rows and human-substituted a, with and
    without fixed blocks, masked and zero rows, row scales 1e-3..1e3."""
    from common.policy.sail import _prepare_np
    rng = np.random.default_rng(seed)
    a, C, c, mask = _random_problem(rng, 40, 25)
    fixed = np.zeros((40, D), bool)
    fixed[::3, 3 * (seed % 3):3 * (seed % 3) + 3] = True
    human = rng.uniform(-0.5, 0.5, (40, D))
    for fm, fa in ((None, None), (fixed, human), (fixed[0], human)):
        got = _prepare_np(a, C, c, mask, 2.0, None, None, fm, fa, SailConfig())
        ref = _prepare_np(a, C, c, mask, 2.0, None, None, fm, fa, SailConfig(), compiled=False)
        assert np.array_equal(got[0], ref[0]) and np.array_equal(got[3], ref[3])
        np.testing.assert_allclose(got[1], ref[1], rtol=1e-14, atol=1e-15)
        np.testing.assert_allclose(got[2], ref[2], rtol=1e-12, atol=1e-12)
        assert np.all(got[1][~got[3]] == 0) and np.all(got[2][~got[3]] == 0)
    with pytest.raises(ValueError, match="fixed_action"):
        _prepare_np(a, C, c, mask, 2.0, None, None, fixed, None, SailConfig())
