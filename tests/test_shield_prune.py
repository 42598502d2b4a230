"""Box-redundant row pruning (common/shield/prune.py) is exact, and the shield
service solves requests of different row counts M in one padded call."""
import inspect
import sys
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

sys.path.insert(0, str(Path(__file__).parent))
from services_fakes import fake_solve, serve_shield  # noqa: E402
from test_services import _ask_concurrently, make_cfg  # noqa: E402

from common import wire  # noqa: E402
from common.safety_rows import SafetyRows  # noqa: E402
from common.shield.prune import DEFAULT_HI, DEFAULT_LO, MARGIN_REL, drop_box_redundant_rows, kept_rows  # noqa: E402
from common.shield.qp import (  # noqa: E402
    STATUS_INFEASIBLE,
    STATUS_OPTIMAL,
    InvalidQPInput,
    QPConfig,
    shield_actions,
    solve_cbf_qp,
)
from services.config import ShieldConfig  # noqa: E402

D = 9
ATOL = 1e-9


# ----------------------------------------------------------------- helpers
def _box_min(C, a, fixed, lo=-1.0, hi=1.0):
    """min over the box (fixed columns at a) of C_j a, per row [B, M]."""
    t = np.where(C > 0, C * lo, C * hi)
    t = np.where(fixed[:, None, :], C * a[:, None, :], t)
    return t.sum(-1)


def _solve(a, rows, backend="default", lo=-1.0, hi=1.0):
    return solve_cbf_qp(a, rows.C, rows.c, rows.row_mask, rows.fixed_mask, lo=lo, hi=hi, backend=backend)


def assert_same_answer(a, rows, backend="default", lo=-1.0, hi=1.0, atol=ATOL):
    """Full rows and pruned rows give the same a_exec, status and slack; returns both."""
    pruned = drop_box_redundant_rows(a, rows, lo=lo, hi=hi)
    full, part = _solve(a, rows, backend, lo, hi), _solve(a, pruned, backend, lo, hi)
    np.testing.assert_array_equal(part.status, full.status)
    np.testing.assert_allclose(part.a_exec, full.a_exec, atol=atol, rtol=0)
    np.testing.assert_allclose(part.slack, full.slack, atol=atol, rtol=0)
    # every row active at the full solution is one the pruned problem kept
    keep = kept_rows(a, rows, lo=lo, hi=hi)
    assert not (full.active & np.asarray(rows.row_mask, bool) & ~keep).any()
    return full, part, pruned


def mixed_problems(rng, B=16, M=30, infeasible=0.3, human=0.4):
    """Random problems mixing rows of every kind the pruning must tell apart:
    tight rows near a safe point, far (redundant) rows, rows touching the box
    exactly at a corner (min over the box = 0), rows just inside and just outside
    the margin, masked-out rows, a fixed human block, opposing infeasible pairs,
    proposals inside, outside and beyond a corner of the box."""
    C = rng.normal(size=(B, M, D)) * rng.choice([0.05, 1.0, 5.0], size=(B, M, 1))
    C[rng.random((B, M, D)) < 0.3] = 0.0
    fixed = np.zeros((B, D), bool)
    for b in np.flatnonzero(rng.random(B) < human):
        s = rng.integers(3)
        fixed[b, 3 * s:3 * s + 3] = True
    x0 = rng.uniform(-0.9, 0.9, (B, D))
    a = np.where(rng.random((B, 1)) < 0.5, rng.uniform(-1.5, 1.5, (B, D)), x0 + 0.4 * rng.normal(size=(B, D)))
    a = np.where(fixed, x0, a)
    scale = np.maximum(1.0, np.linalg.norm(C, axis=-1))
    bmin = _box_min(C, a, fixed)
    kind = rng.integers(0, 6, size=(B, M))
    c = np.einsum("bmd,bd->bm", C, x0) - rng.uniform(0.0, 0.4, (B, M))              # 0: tight at x0
    c = np.where(kind == 1, bmin - rng.uniform(1e-5, 2.0, (B, M)) * scale, c)         # 1: far, redundant
    c = np.where(kind == 2, bmin, c)                                                  # 2: touches a corner
    c = np.where(kind == 3, bmin - 0.5 * MARGIN_REL * scale, c)                       # 3: inside the margin
    c = np.where(kind == 4, bmin - 3.0 * MARGIN_REL * scale, c)                       # 4: just outside it
    mask = rng.random((B, M)) < 0.85                                                  # 5: tight, often masked
    # a proposal beyond a corner-touching row's corner: the projection lands on that corner
    for b in np.flatnonzero(rng.random(B) < 0.25):
        j = np.flatnonzero(kind[b] == 2)
        if len(j):
            corner = np.where(C[b, j[0]] > 0, -1.0, 1.0)
            a[b] = np.where(fixed[b], a[b], 1.4 * corner)
            mask[b, j[0]] = True
    # infeasible: n·a >= t + g and n·a <= t
    for b in np.flatnonzero(rng.random(B) < infeasible):
        n = rng.normal(size=D)
        n[fixed[b]] = 0.0
        t, g = rng.uniform(-0.3, 0.3), rng.uniform(0.05, 0.5)
        C[b, :2], c[b, :2], mask[b, :2] = np.stack([n, -n]), [t + g, -t], True
    return a, SafetyRows(C, c, mask, fixed)


# ----------------------------------------------------------------- the pruning itself
def test_default_box_is_the_shields_and_margin_exceeds_every_qp_tolerance():
    p = inspect.signature(solve_cbf_qp).parameters
    assert (DEFAULT_LO, DEFAULT_HI) == (p["lo"].default, p["hi"].default)
    assert inspect.signature(drop_box_redundant_rows).parameters["lo"].default == p["lo"].default
    assert inspect.signature(drop_box_redundant_rows).parameters["hi"].default == p["hi"].default
    cfg = QPConfig()
    assert MARGIN_REL > 5 * max(cfg.tol, cfg.active_tol)


def test_random_mixed_problems_same_answer_default_backend():
    rng = np.random.default_rng(0)
    n_inf = n_drop = n_rows = 0
    for _ in range(20):
        a, rows = mixed_problems(rng)
        full, _, pruned = assert_same_answer(a, rows)
        n_inf += int((full.status == STATUS_INFEASIBLE).sum())
        n_rows += int(rows.row_mask.sum())
        n_drop += int(rows.row_mask.sum() - pruned.row_mask.sum())
        assert pruned.n_rows < rows.n_rows
    assert n_inf > 20 and 0 < n_drop < n_rows   # both cases exercised, and pruning does something


def test_per_problem_box_same_answer_and_bad_box_refused():
    rng = np.random.default_rng(4)
    a, rows = mixed_problems(rng, B=12)
    lo = -rng.uniform(0.3, 1.0, (12, D))
    hi = rng.uniform(0.3, 1.0, (12, D))
    assert_same_answer(a, rows, lo=lo, hi=hi)
    assert_same_answer(a, rows, lo=lo[0], hi=hi[0])   # [d]
    for bad_lo, bad_hi in ((-np.inf, 1.0), (0.5, 0.4), (np.nan, 1.0)):
        with pytest.raises(InvalidQPInput):
            drop_box_redundant_rows(a, rows, lo=bad_lo, hi=bad_hi)
    with pytest.raises(InvalidQPInput):
        drop_box_redundant_rows(a[:3], rows)


def test_osqp_backend_same_answer_on_a_few_cases():
    rng = np.random.default_rng(1)
    for _ in range(2):
        a, rows = mixed_problems(rng, B=8, infeasible=0.4)
        full, _, _ = assert_same_answer(a, rows, backend="osqp", atol=1e-8)
        assert (full.status == STATUS_OPTIMAL).any() and (full.status == STATUS_INFEASIBLE).any()


def test_margin_matters_corner_rows_are_kept_and_active():
    # one free problem, a proposal beyond the corner (1, -1, 1, ...): the answer is the corner
    corner = np.array([1.0, -1.0] * 4 + [1.0])
    a = 1.5 * corner[None]
    Cr = np.array([[-1.0, 1.0] * 4 + [-1.0]])                   # min over box at `corner`
    g = np.array([0.0, 0.5 * MARGIN_REL, 2 * MARGIN_REL, 0.1])  # distance of the box from each row
    scale = np.linalg.norm(Cr)
    C = np.repeat(Cr[None], 4, axis=1)
    c = (Cr @ corner) - g[None] * scale
    rows = SafetyRows(C, c, np.ones((1, 4), bool), np.zeros((1, D), bool))
    np.testing.assert_array_equal(kept_rows(a, rows), [[True, True, False, False]])
    full, part, pruned = assert_same_answer(a, rows)
    np.testing.assert_allclose(full.a_exec[0], corner, atol=1e-12)
    assert full.active[0, 0] and pruned.n_rows == 2
    # the same rows with a slightly smaller box: now even the corner row is slack by > margin
    assert not kept_rows(a, rows, lo=-0.99, hi=0.99).any()
    assert_same_answer(a, rows, lo=-0.99, hi=0.99)


def test_fixed_block_enters_with_the_proposals_values():
    # row a_0 + a_3 >= c with a_3 fixed: redundant or not depending on a_prop[3]
    C = np.zeros((2, 1, D))
    C[:, 0, [0, 3]] = 1.0
    c = np.array([[-0.5], [-0.5]])
    fixed = np.zeros((2, D), bool)
    fixed[:, 3:6] = True
    a = np.zeros((2, D))
    a[0, 3], a[1, 3] = 0.9, 0.1      # min: -1 + 0.9 = -0.1 > -0.5 (drop) vs -0.9 < -0.5 (keep)
    rows = SafetyRows(C, c, np.ones((2, 1), bool), fixed)
    np.testing.assert_array_equal(kept_rows(a, rows), [[False], [True]])
    assert_same_answer(a, rows)


def test_layout_shapes_dtypes_and_padding():
    rng = np.random.default_rng(2)
    a, rows = mixed_problems(rng, B=6, M=12)
    rows = SafetyRows(rows.C.astype(np.float32), rows.c.astype(np.float32), rows.row_mask, rows.fixed_mask)
    keep = kept_rows(a, rows)
    p = drop_box_redundant_rows(a, rows)
    assert p.C.dtype == np.float64 and p.c.dtype == np.float64
    assert p.row_mask.dtype == bool and p.fixed_mask.dtype == bool
    assert p.C.shape == (6, keep.sum(1).max(), D) and p.c.shape == p.row_mask.shape == p.C.shape[:2]
    assert p.fixed_mask.shape == (6, D)
    for b in range(6):
        k = int(keep[b].sum())
        np.testing.assert_array_equal(p.C[b, :k], rows.C[b][keep[b]])     # compacted, original order
        np.testing.assert_array_equal(p.c[b, :k], rows.c[b][keep[b]])
        assert p.row_mask[b, :k].all() and not p.row_mask[b, k:].any()
        assert (p.C[b, k:] == 0).all() and (p.c[b, k:] == 0).all()
    # all rows redundant or masked: one padding row; an empty M works too
    none = SafetyRows(np.zeros((3, 5, D)), -np.ones((3, 5)), np.ones((3, 5), bool), np.zeros(D, bool))
    q = drop_box_redundant_rows(np.zeros((3, D)), none)
    assert q.C.shape == (3, 1, D) and not q.row_mask.any() and q.fixed_mask.shape == (3, D)
    e = drop_box_redundant_rows(np.zeros((2, D)), SafetyRows(np.zeros((2, 0, D)), np.zeros((2, 0)),
                                                             np.zeros((2, 0), bool), np.zeros((2, D), bool)))
    assert e.C.shape == (2, 1, D) and not e.row_mask.any()
    # the pruned rows pass the wire's schema for a shield request
    body = {"a_prop": a, **p.as_dict()}
    dec = wire.decode(wire.encode("shield_req", body, run_id="r", sender="a", seq=0), run_id="r",
                      expect="shield_req").body
    np.testing.assert_array_equal(dec["C"], p.C)


def test_nonfinite_rows_are_kept_so_the_solver_still_rejects_them():
    C = np.zeros((1, 3, D))
    C[0, 1, 0] = np.nan
    c = -np.ones((1, 3))
    rows = SafetyRows(C, c, np.array([[True, False, True]]), np.zeros((1, D), bool))
    p = drop_box_redundant_rows(np.zeros((1, D)), rows)
    assert p.C.shape[1] == 1 and np.isnan(p.C).any() and not p.row_mask.any()
    with pytest.raises(InvalidQPInput):
        _solve(np.zeros((1, D)), p)


def test_safety_rows_padded_and_concat_pad():
    rng = np.random.default_rng(3)
    a1, r1 = mixed_problems(rng, B=3, M=4, infeasible=0.0)
    a2, r2 = mixed_problems(rng, B=2, M=7, infeasible=0.0)
    assert r1.padded(4) is r1
    with pytest.raises(ValueError):
        r2.padded(3)
    with pytest.raises(ValueError):
        SafetyRows.concat([r1, r2])
    both = SafetyRows.concat([r1, r2], pad=True)
    assert both.C.shape == (5, 7, D) and not both.row_mask[:3, 4:].any() and (both.C[:3, 4:] == 0).all()
    joint = _solve(np.concatenate([a1, a2]), both)
    for sl, a, r in ((slice(0, 3), a1, r1), (slice(3, 5), a2, r2)):
        alone = _solve(a, r)
        np.testing.assert_allclose(joint.a_exec[sl], alone.a_exec, atol=1e-12, rtol=0)
        np.testing.assert_array_equal(joint.status[sl], alone.status)


# ----------------------------------------------------------------- hypothesis
unit = st.floats(-1.0, 1.0, allow_nan=False, allow_subnormal=False)


@st.composite
def pruning_problem(draw):
    """Feasible rows around a safe point (Slater margin, as in test_qp_properties),
    optionally an opposing infeasible pair, plus rows placed relative to the box:
    touching it (0), within the margin, just past it, or far from it."""
    M = draw(st.integers(1, 10))
    x0 = draw(arrays(np.float64, D, elements=st.floats(-0.9, 0.9)))
    C = draw(arrays(np.float64, (M, D), elements=unit))
    slater = draw(arrays(np.float64, M, elements=st.floats(1e-6, 0.5)))
    a = draw(arrays(np.float64, D, elements=st.floats(-1.5, 1.5)))
    fixed = np.zeros(D, bool)
    slot = draw(st.sampled_from([None, 0, 1, 2]))
    if slot is not None:
        fixed[3 * slot:3 * slot + 3] = True
    a = np.where(fixed, x0, a)
    c = C @ x0 - slater
    mask = draw(arrays(np.bool_, M))
    R = draw(st.integers(0, 8))
    Cr = draw(arrays(np.float64, (R, D), elements=unit))
    off = draw(arrays(np.float64, R, elements=st.sampled_from([0.0, 0.3, 0.99, 1.01, 3.0, 1e3, 1e6])))
    scale = np.maximum(1.0, np.linalg.norm(Cr, axis=-1))
    cr = _box_min(Cr[None], a[None], fixed[None])[0] - off * MARGIN_REL * scale
    C, c = np.concatenate([C, Cr]), np.concatenate([c, cr])
    mask = np.concatenate([mask, draw(arrays(np.bool_, R))])
    if draw(st.booleans()):
        n = draw(arrays(np.float64, D, elements=unit).filter(lambda v: np.linalg.norm(v) > 0.3))
        n = np.where(fixed, 0.0, n)
        t, g = draw(st.floats(-0.5, 0.5)), draw(st.floats(0.05, 0.5))
        C, c = np.concatenate([C, [n, -n]]), np.concatenate([c, [t + g, -t]])
        mask = np.concatenate([mask, [True, True]])
    return a[None], SafetyRows(C[None], c[None], mask[None], fixed[None])


@settings(max_examples=200, deadline=None)
@given(pruning_problem())
def test_hypothesis_pruned_rows_give_the_same_answer(prob):
    a, rows = prob
    assert_same_answer(a, rows)


# ----------------------------------------------------------------- real env rows
def _env_rows(scenario, K=8, steps=40, human_slot=None, seed=0):
    """(a_prop, rows) of a shielded rollout: even envs follow the scripted route with
    noise, odd ones push in a constant random direction (into walls: active rows)."""
    from common.env.batch_env import BatchEnv
    from common.env.config import EnvConfig

    env = BatchEnv(EnvConfig(scenario, human_slot=human_slot), num_envs=K, seed=seed)
    rng = np.random.default_rng(seed)
    push = rng.uniform(-1, 1, (K, D))
    push[:, 2::3] = 0.0
    out = env.reset()
    for _ in range(steps):
        rows = SafetyRows.of(out)
        a = np.where(np.arange(K)[:, None] % 2 == 0, env.scripted_actions() + 0.4 * rng.normal(size=(K, D)), push)
        a = np.clip(a, -1, 1)
        a = np.where(rows.fixed_mask, out["human_action"], a)
        yield a, rows
        out = env.step(shield_actions(a, rows).a_exec)


@pytest.mark.parametrize("scenario,human_slot", [("narrow_gate", None), ("maze", 1)])
def test_real_env_rows_keep_every_active_row_and_shrink_the_message(scenario, human_slot):
    m_full = m_kept = bytes_full = bytes_pruned = n_active = 0
    for a, rows in _env_rows(scenario, human_slot=human_slot):
        full, _, pruned = assert_same_answer(a, rows)
        n_active += int((full.active & rows.row_mask).sum())
        m_full += rows.n_rows
        m_kept += pruned.n_rows
        enc = lambda r: len(wire.encode("shield_req", {"a_prop": a, **r.as_dict()},  # noqa: E731
                                        run_id="r", sender="actor/0", seq=0))
        bytes_full += enc(rows)
        bytes_pruned += enc(pruned)
    print(f"\n{scenario}: M {m_full / 40:.1f} -> M' {m_kept / 40:.2f}, "
          f"shield_req {bytes_full / 40:.0f} -> {bytes_pruned / 40:.0f} B, active rows seen {n_active}")
    assert n_active > 0 and bytes_pruned < 0.5 * bytes_full


# ----------------------------------------------------------------- the shield service
def _pruned_requests():
    rng = np.random.default_rng(5)
    reqs = []
    for n, M in ((3, 9), (2, 20)):
        a, rows = mixed_problems(rng, B=n, M=M)
        p = drop_box_redundant_rows(a, rows)
        reqs.append({"a_prop": a, **p.as_dict()})
    assert reqs[0]["C"].shape[1] != reqs[1]["C"].shape[1]
    return reqs


def test_shield_service_solves_requests_of_different_m_in_one_call(tmp_path, bus):
    cfg = make_cfg(tmp_path, run_id="tp", shield=ShieldConfig(max_batch=1000, window_s=30.0))  # closes at 2 askers
    calls = []

    def spy(a_prop, rows):
        calls.append(rows.C.shape)
        return shield_actions(a_prop, rows)

    shield, stop, th = serve_shield(cfg, bus, spy)
    calls.clear()  # the warm-up solve
    reqs = _pruned_requests()
    replies = _ask_concurrently(cfg, bus, reqs)
    stop.set()
    th.join(5)
    M = max(r["C"].shape[1] for r in reqs)
    assert calls == [(5, M, D)]   # one solve, padded to the largest M
    for r, rep in zip(reqs, replies):
        body = wire.decode(rep.ok, run_id=cfg.run_id, expect="shield_rep").body
        alone = shield_actions(r["a_prop"], SafetyRows.of(r))
        np.testing.assert_allclose(body["a_exec"], alone.a_exec, atol=1e-12, rtol=0)
        np.testing.assert_array_equal(body["status"], alone.status)
        np.testing.assert_allclose(body["slack"], alone.slack, atol=1e-12, rtol=0)
        np.testing.assert_allclose(body["correction_norm"], alone.correction_norm, atol=1e-12, rtol=0)
        assert body["batch_size"] == 5
    assert shield.n_rows == 5 and shield.busy_s > 0


def test_shield_service_isolates_a_failing_request_after_a_failed_joint_solve(tmp_path, bus):
    cfg = make_cfg(tmp_path, run_id="tp", shield=ShieldConfig(max_batch=1000, window_s=30.0))
    reqs = _pruned_requests()
    reqs[1]["a_prop"] = np.full_like(reqs[1]["a_prop"], 0.125)   # the marker the solver refuses
    calls = []

    def picky(a_prop, rows):
        calls.append(a_prop.shape[0])
        if (a_prop == 0.125).all(axis=1).any():
            raise ValueError("refused")
        return fake_solve(a_prop, rows)

    shield, stop, th = serve_shield(cfg, bus, picky)
    calls.clear()
    replies = _ask_concurrently(cfg, bus, reqs)
    stop.set()
    th.join(5)
    assert sorted(calls) == [2, 3, 5]   # joint, then one by one
    assert replies[0].ok is not None and replies[1].err.startswith(b"invalid_input")
    body = wire.decode(replies[0].ok, run_id=cfg.run_id, expect="shield_rep").body
    np.testing.assert_allclose(body["a_exec"], fake_solve(reqs[0]["a_prop"], SafetyRows.of(reqs[0])).a_exec)
