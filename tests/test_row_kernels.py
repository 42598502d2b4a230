"""The compiled row kernels (common/shield/row_kernels.py) equal their numpy
references: row pruning (prune.drop_box_redundant_rows vs reference.drop_box_redundant_rows) and
the actor's answer check (verify.verify_answer vs its numpy path verify_answer_fallback),
on random problems of every row kind, real env rows and every kind of bad answer."""
import sys
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

sys.path.insert(0, str(Path(__file__).parent))
from test_shield_prune import _env_rows, mixed_problems, pruning_problem  # noqa: E402

from common.safety_rows import SafetyRows  # noqa: E402
from common.shield import reference  # noqa: E402
from common.shield.prune import drop_box_redundant_rows  # noqa: E402
from common.shield.qp import STATUS_INFEASIBLE, STATUS_MAX_ITER, STATUS_OPTIMAL, shield_actions  # noqa: E402
from common.shield.row_kernels import check_answer_kernel  # noqa: E402
from common.shield.verify import verify_answer, verify_answer_fallback  # noqa: E402

D = 9


def assert_same_pruning(a, rows):
    got, ref = drop_box_redundant_rows(a, rows), reference.drop_box_redundant_rows(a, rows)
    for name in ("C", "c", "row_mask", "fixed_mask"):
        x, y = getattr(got, name), getattr(ref, name)
        assert x.dtype == y.dtype and x.shape == y.shape, name
        np.testing.assert_array_equal(x, y, err_msg=name)


@pytest.mark.parametrize("seed", range(6))
def test_pruning_kernel_equals_reference_on_mixed_problems(seed):
    assert_same_pruning(*mixed_problems(np.random.default_rng(seed)))


@settings(max_examples=150, deadline=None)
@given(pruning_problem())
@pytest.mark.sweep
def test_pruning_kernel_equals_reference_hypothesis(prob):
    assert_same_pruning(*prob)


def test_pruning_kernel_equals_reference_with_nonfinite_entries_and_broadcast_masks():
    rng = np.random.default_rng(3)
    a, rows = mixed_problems(rng, B=8)
    C, c, a = rows.C.copy(), rows.c.copy(), a.copy()
    C[0, 1, 2], c[1, 3], C[2, 0, 0] = np.nan, np.inf, -np.inf
    assert_same_pruning(a, SafetyRows(C, c, rows.row_mask, rows.fixed_mask))
    # a NaN in a fixed (human) column poisons the rounding bound: nothing is dropped, as in numpy
    fixed = np.zeros(D, bool)
    fixed[:3] = True
    a[4, 0] = np.nan
    assert_same_pruning(a, SafetyRows(C, c, rows.row_mask, fixed))     # [d] fixed mask, broadcast
    assert_same_pruning(a, SafetyRows(C, c, np.ones(c.shape[1], bool), rows.fixed_mask))


@pytest.mark.parametrize("scenario,human_slot", [("narrow_gate", None), ("maze", 1)])
def test_pruning_kernel_equals_reference_on_env_rows(scenario, human_slot):
    for a, rows in _env_rows(scenario, K=8, steps=25, human_slot=human_slot):
        assert_same_pruning(a, rows)


# ----------------------------------------------------------------- the answer check
def _answers(a, rows, rng):
    """(name, (a_exec, status)): the real shield answer and every kind of bad
    one: out of the box, a touched human block, unknown or uncertified status,
    violated rows, NaN, false and true infeasibility claims, float status."""
    res = shield_actions(a, rows)
    good = (np.asarray(res.a_exec, np.float64), np.asarray(res.status, np.int32))
    yield "good", good
    x, s = good[0].copy(), good[1].copy()
    free = np.flatnonzero(~np.broadcast_to(rows.fixed_mask, a.shape)[0])
    x[0, free[0]] = 1.0 + 1e-3
    yield "box", (x, s)
    x = good[0].copy()
    b = int(np.flatnonzero(np.asarray(rows.fixed_mask).any(1))[0])
    x[b, np.flatnonzero(rows.fixed_mask[b])[0]] += 1e-12
    yield "fixed", (x, s)
    yield "maxiter", (good[0], np.where(np.arange(len(s)) == 2, STATUS_MAX_ITER, s).astype(np.int32))
    yield "unknown status", (good[0], np.where(np.arange(len(s)) == 3, 7, s).astype(np.int32))
    x = good[0].copy()
    x[5, 0] = np.nan
    yield "nan", (x, s)
    yield "proposals as answers", (np.clip(a, -1, 1), np.zeros(len(s), np.int32))
    yield "everything claimed infeasible", (good[0], np.full(len(s), STATUS_INFEASIBLE, np.int32))
    yield "float status", (good[0], s.astype(np.float64))
    yield "random", (rng.uniform(-1, 1, a.shape), rng.integers(0, 2, len(s)).astype(np.int32))


@pytest.mark.parametrize("seed", range(5))
def test_answer_check_kernel_equals_reference(seed):
    rng = np.random.default_rng(seed)
    a, rows = mixed_problems(rng, B=12, infeasible=0.3, human=0.5)
    verdicts = {}
    for name, (x, s) in _answers(a, rows, rng):
        got = verify_answer(a, rows, x, s)
        assert got == verify_answer_fallback(a, rows, x, s), name
        verdicts[name] = got
    assert verdicts["good"] is None and verdicts["box"] == "box" and verdicts["fixed"] == "fixed_block"
    assert verdicts["maxiter"] == verdicts["unknown status"] == "status" and verdicts["nan"] == "nonfinite"


def test_answer_check_kernel_violation_equals_scaled_violation():
    rng = np.random.default_rng(11)
    a, rows = mixed_problems(rng, B=16)
    x = rng.uniform(-1, 1, a.shape)
    fixed = np.broadcast_to(rows.fixed_mask, a.shape)
    _, violation = check_answer_kernel(a, x, np.zeros(len(a), np.int64), rows.C, rows.c,
                                       np.ascontiguousarray(rows.row_mask), np.ascontiguousarray(fixed),
                                       1e-6, STATUS_OPTIMAL, STATUS_INFEASIBLE)
    np.testing.assert_allclose(violation, rows.scaled_violation(x), rtol=1e-12, atol=1e-12)
    none = SafetyRows(rows.C, rows.c, np.zeros_like(rows.row_mask), rows.fixed_mask)
    _, violation = check_answer_kernel(a, x, np.zeros(len(a), np.int64), none.C, none.c, none.row_mask,
                                       np.ascontiguousarray(fixed), 1e-6, STATUS_OPTIMAL, STATUS_INFEASIBLE)
    assert np.all(violation == -np.inf) and np.all(none.scaled_violation(x) == -np.inf)


@settings(max_examples=150, deadline=None)
@given(pruning_problem(), st.integers(0, 2**32 - 1),
       arrays(np.float64, D, elements=st.floats(-1.2, 1.2)))
@pytest.mark.sweep
def test_answer_check_kernel_equals_reference_hypothesis(prob, seed, jitter):
    """Answers near the real one (some inside tol, some beyond) and arbitrary statuses."""
    a, rows = prob
    res = shield_actions(a, rows)
    rng = np.random.default_rng(seed)
    scale = rng.choice([0.0, 1e-9, 1e-5, 1e-2, 1.0])
    x = np.asarray(res.a_exec, np.float64) + scale * jitter[None]
    x = np.where(np.broadcast_to(rows.fixed_mask, a.shape), a, x)
    s = np.asarray(res.status, np.int32) if rng.random() < 0.7 else rng.integers(0, 3, 1).astype(np.int32)
    assert verify_answer(a, rows, x, s) == verify_answer_fallback(a, rows, x, s)
