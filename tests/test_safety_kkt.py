"""The actor executes only the exact QP's answer (issue 32, defect 1): a
feasible but wrong answer claimed OPTIMAL ("all zeros, optimal", a point
inside the safe set) fails the KKT check of Eq. (qpshield) and is refused as
``kkt``, while every real answer passes: random problems of every row kind,
the human carrier's exogenous block, answers to pruned queries, both backends
and real env rows."""
import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).parent))
from test_shield_prune import _env_rows, mixed_problems  # noqa: E402

from common.safety_rows import SafetyRows  # noqa: E402
from common.shield.prune import drop_box_redundant_rows  # noqa: E402
from common.shield.qp import BACKENDS, STATUS_OPTIMAL, shield_actions  # noqa: E402
from common.shield.verify import verify_answer, verify_answer_fallback  # noqa: E402

D = 9


def _both(a, rows, x, s):
    got = verify_answer(a, rows, x, s)
    assert got == verify_answer_fallback(a, rows, x, s)
    return got


def _zero_feasible_rows(rng, B=16, M=20, human=False):
    """CBF-like rows every one of which a = 0 meets strictly, and proposals
    outside some of them: zero is safe but not the projection."""
    C = rng.normal(size=(B, M, D))
    a = rng.uniform(-1, 1, (B, D))
    c = np.minimum(np.einsum("bmd,bd->bm", C, a) + rng.uniform(0.05, 0.5, (B, M)), -1e-3)
    c = np.where(rng.random((B, M)) < 0.6, c, -rng.uniform(0.5, 2, (B, M)))
    fixed = np.zeros((B, D), bool)
    if human:
        fixed[::2, 6:9] = True
        a[::2, 6:9] = 0.0   # a human standing still: zero on the fixed block stays "plausible"
    return a, SafetyRows(C, c, np.ones((B, M), bool), fixed)


@pytest.mark.parametrize("human", [False, True], ids=["carriers", "human"])
def test_all_zeros_claimed_optimal_is_refused_as_kkt(human):
    a, rows = _zero_feasible_rows(np.random.default_rng(0), human=human)
    zeros, optimal = np.zeros_like(a), np.zeros(len(a), np.int32)
    assert np.all(rows.scaled_violation(zeros) < 0)            # the forgery meets every row ...
    assert _both(a, rows, zeros, optimal) == "kkt"              # ... and is still refused
    res = shield_actions(a, rows)
    assert (res.status == STATUS_OPTIMAL).all()
    assert _both(a, rows, res.a_exec, res.status.astype(np.int32)) is None


def test_feasible_points_near_but_not_at_the_projection_are_refused():
    rng = np.random.default_rng(1)
    a, rows = _zero_feasible_rows(rng)
    x = shield_actions(a, rows).a_exec
    s = np.zeros(len(a), np.int32)
    for t in (1e-3, 1e-1, 0.5):   # toward the (strictly feasible) origin: still safe, not the QP's answer
        assert _both(a, rows, (1 - t) * x, s) == "kkt", t
    # one problem wrong is enough to refuse the batch
    y = x.copy()
    y[3] *= 0.9
    assert _both(a, rows, y, s) == "kkt"


@pytest.mark.parametrize("seed", range(4))
@pytest.mark.parametrize("backend", sorted(BACKENDS))
def test_real_answers_pass_on_every_row_kind_full_and_pruned(seed, backend):
    a, rows = mixed_problems(np.random.default_rng(seed), B=24, infeasible=0.3, human=0.5)
    assert np.asarray(rows.fixed_mask).any()
    for query in (rows, drop_box_redundant_rows(a, rows)):   # the shield may be asked with pruned rows
        res = shield_actions(a, query, backend=backend)
        assert _both(a, rows, res.a_exec, res.status.astype(np.int32)) is None


@pytest.mark.parametrize("scenario,human_slot", [("narrow_gate", None), ("maze", 1)])
def test_real_answers_pass_on_env_rows(scenario, human_slot):
    n = 0
    for a, rows in _env_rows(scenario, K=8, steps=25, human_slot=human_slot):
        res = shield_actions(a, drop_box_redundant_rows(a, rows))
        assert verify_answer(a, rows, res.a_exec, res.status.astype(np.int32)) is None
        zeros = np.where(np.broadcast_to(rows.fixed_mask, a.shape), a, 0.0)
        if np.all(rows.scaled_violation(zeros) <= 0) and np.abs(zeros - res.a_exec).max() > 1e-4:
            assert verify_answer(a, rows, zeros, np.zeros(len(a), np.int32)) == "kkt"
            n += 1
    assert n > 0    # the plausible forgery was tried on real rows
