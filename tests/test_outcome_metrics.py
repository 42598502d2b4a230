"""How episodes end and how often they leave the shield's safe set (common/env/metrics.py,
BatchEnv's episode records, common/evaluation/deployment.py): the margin violation's
tolerance, pooled Col./1k beside the per-episode mean, truncation (timeout / deadlock)
apart from drops and collisions."""
from __future__ import annotations

import math

import numpy as np
import pytest

from common.env.batch_env import BatchEnv
from common.env.config import EnvConfig
from common.env.metrics import aggregate, margin_violation

BASE = dict(completion_time=math.nan, tilt=0.0, heading_error=0.0, height_error=0.0, min_clearance=0.1,
            progress_per_step=0.01, final_progress=0.5, **{"return": 0.0})


def record(steps, collisions=0, margin=0, success=False, drop=False, truncated=None, deadlock=False):
    truncated = (not success and not drop) if truncated is None else truncated
    return dict(BASE, steps=steps, collision_steps=collisions, col_per_1k=1000.0 * collisions / steps,
                margin_violation_steps=margin, margin_col_per_1k=1000.0 * margin / steps, success=success,
                drop=drop, truncated=truncated, deadlock=deadlock)


# ----------------------------------------------------------------------------- margin tolerance

def test_margin_violation_needs_the_barrier_below_minus_the_tolerance():
    tol = EnvConfig().margin_violation_tol
    assert tol == 0.005
    barrier = np.array([-5e-8, -1.9e-3, -0.005, -0.0051, -0.01, 0.0, 0.3])
    np.testing.assert_array_equal(margin_violation(barrier, tol),
                                  [False, False, False, True, True, False, False])
    np.testing.assert_array_equal(margin_violation(barrier, 0.0), [True, True, True, True, True, False, False])


@pytest.mark.parametrize("tol,want", [(0.005, [False, True]), (0.0, [True, True])])
def test_env_counts_margin_violations_with_its_configured_tolerance(tol, want, monkeypatch):
    """A QP answer at its row's boundary (barrier -5e-8 m after the step) is no violation;
    a centimetre past it is. The env's flag and the episode's count use the config's tol."""
    env = BatchEnv(EnvConfig("narrow_gate", randomize=False, max_steps=3, margin_violation_tol=tol), 2, seed=0)
    env.reset()
    monkeypatch.setattr(env._safety_model, "barrier_min", lambda *a: np.array([-5e-8, -0.01]))
    episodes = []
    for _ in range(3):
        out = env.step(np.zeros((2, 9)))
        np.testing.assert_array_equal(out["margin_violation"], want)
        episodes += out["episodes"]
    assert [e["margin_violation_steps"] for e in episodes] == [3 * w for w in want]


def test_bad_outcome_settings_are_refused():
    for bad in (dict(margin_violation_tol=-0.001), dict(deadlock_window_s=0.0), dict(deadlock_move_xy=-1.0),
                dict(margin_violation_tol=math.nan)):
        with pytest.raises(ValueError):
            EnvConfig(**bad)


# ----------------------------------------------------------------------------- pooled Col./1k

def test_pooled_col_per_1k_is_collision_steps_over_all_steps():
    """A short crash and a long clean run: the per-episode mean weighs the crash's rate
    like the clean run's; the pooled figure divides all collision steps by all steps."""
    eps = [record(20, collisions=10, margin=12, drop=True), record(980, collisions=0, margin=2, success=True)]
    agg = aggregate(eps)
    assert agg["col_per_1k"] == pytest.approx((500.0 + 0.0) / 2)
    assert agg["col_per_1k_pooled"] == pytest.approx(1000.0 * 10 / 1000)
    assert agg["margin_col_per_1k"] == pytest.approx((600.0 + 1000.0 * 2 / 980) / 2)
    assert agg["margin_col_per_1k_pooled"] == pytest.approx(1000.0 * 14 / 1000)


# ----------------------------------------------------------------------------- truncation apart

def test_success_drop_and_truncation_partition_the_episodes():
    eps = [record(100, success=True), record(50, drop=True, collisions=5), record(300, deadlock=True),
           record(300), record(300, deadlock=True)]
    agg = aggregate(eps)
    assert (agg["success_rate"], agg["drop_rate"], agg["truncation_rate"]) == (0.2, 0.2, 0.6)
    assert agg["success_rate"] + agg["drop_rate"] + agg["truncation_rate"] == pytest.approx(1.0)
    assert agg["deadlock_rate"] == pytest.approx(0.4) and agg["timeout_rate"] == pytest.approx(0.2)
    # records written before these fields: truncated = neither success nor drop; deadlock unknown
    old = [{k: v for k, v in e.items() if k not in ("truncated", "deadlock")} for e in eps]
    agg_old = aggregate(old)
    assert agg_old["truncation_rate"] == 0.6
    assert math.isnan(agg_old["deadlock_rate"]) and math.isnan(agg_old["timeout_rate"])
    assert math.isnan(aggregate([])["truncation_rate"])


def test_env_tells_a_deadlock_from_a_timeout():
    """Two envs to the same time limit: one team stands still (deadlock), one follows the
    scripted controller but runs out of time before the goal (timeout)."""
    cfg = EnvConfig("narrow_gate", randomize=False, max_steps=60)
    assert cfg.max_steps * cfg.control_dt >= cfg.deadlock_window_s
    env = BatchEnv(cfg, 2, seed=0)
    env.reset()
    episodes = []
    for _ in range(60):
        a = env.scripted_actions()
        a[0] = 0.0
        episodes += env.step(a)["episodes"]
    assert len(episodes) == 2
    still, moving = episodes
    for e in episodes:
        assert e["truncated"] and not e["success"] and not e["drop"]
    assert still["deadlock"] and not moving["deadlock"]
    assert moving["final_progress"] > 0.2 and still["final_progress"] < 0.05


def test_deployment_evaluation_reports_truncation_apart():
    from common.evaluation.deployment import evaluate_policy
    from services.config import TrainConfig
    from services.learner.service import build_method

    cfg = TrainConfig(run_id="t", method="happo_cbf").resolve()
    params = build_method(cfg).policy_params()        # untrained: it will not reach the goal in 30 steps
    env_cfg = EnvConfig("narrow_gate", max_steps=30)
    res = evaluate_policy(params, env_cfg, 3, seed=3, shielded=True)
    assert res["episodes"] == 3
    assert res["success_rate"] + res["drop_rate"] + res["truncation_rate"] == pytest.approx(1.0)
    assert res["truncation_rate"] > 0
    assert res["timeout_rate"] + res["deadlock_rate"] == pytest.approx(res["truncation_rate"])
    assert "col_per_1k_pooled" in res and "margin_col_per_1k_pooled" in res
    # `sage eval` and the suite's result records carry them
    from sage.evaluate import eval_record
    rec = eval_record(res)
    for key in ("truncation_rate", "timeout_rate", "deadlock_rate", "col_per_1k_pooled", "margin_col_per_1k_pooled",
                "margin_violation_steps", "success_rate", "drop_rate"):
        assert rec[key] == res[key], key
