"""Predictor honesty (common/evaluation/honesty.py): shielded random actions vs the true next-state barriers."""
import numpy as np
import pytest

from common.env import safety
from common.env.layout import PAIR_REST
from common.evaluation.honesty import _PredictorWorld, measure_honesty, row_barriers


@pytest.mark.parametrize("rows", ["paper", "grasp"])
def test_row_barrier_lookup_reproduces_row_h(rows):
    """Looking each row's barrier up in barrier_values gives the h that build_rows reports."""
    w = _PredictorWorld("chicane", num_envs=4, seed=3, safety_rows=rows)
    rng = np.random.default_rng(0)
    for _ in range(5):  # a few predictor steps so the formation is no longer at rest
        w.step(rng.uniform(-1, 1, (4, 9)) * 0.3)
    geom = w.geometry()
    C, c, mask, info = safety.build_rows(geom, w.walls, w.cfg)
    looked_up = row_barriers(safety.barrier_values(geom, w.walls, w.cfg), info, w.cfg.max_rows)
    assert mask.any(1).all() and (info["kind"][mask] != safety.KIND_FORMATION).any()
    assert np.allclose(looked_up[mask], info["h"][mask], atol=1e-12)
    assert (info["kind"][mask] == safety.KIND_FORMATION).any() == (rows == "grasp")


def test_predictor_world_rows_hold_by_construction():
    # the "grasp" profile, so the formation rows (lower conservative, upper first-order) are measured too
    r = measure_honesty("narrow_gate", n_steps=60, seed=0, num_envs=6, world="predictor", safety_rows="grasp")
    print(f"\npredictor-world honesty narrow_gate: rate={r['rate']:.4f} row_rate={r['row_rate']}")
    assert r["active"] > 0 and r["row_count"]["carrier_wall"] > 0 and r["row_count"]["payload_wall"] > 0
    assert r["infeasible"] == 0 and r["rows_match"] == r["transitions"]
    # conservative rows (supporting half-planes of convex sets, lower formation) never miss
    for kind in ("carrier_wall", "payload_wall", "formation_lo"):
        assert r["row_rate"][kind] == 1.0, kind
    assert r["unsafe_by"]["carrier_wall"] == 0 and r["unsafe_by"]["payload_wall"] == 0
    # the upper formation row is first-order: misses are at most |δ⊥|²/(2D) <= 4 s²/(D0_min - tol)
    cfg = _PredictorWorld("narrow_gate", 1, 0, safety_rows="grasp").cfg
    bound = 4 * cfg.max_step_xy ** 2 / (PAIR_REST.min() - cfg.grasp_tol)
    assert r["min_next_h"] >= -bound
    assert r["rate"] >= 0.9


@pytest.mark.parametrize("scenario", ["narrow_gate", "l_corridor"])
def test_mujoco_honesty_rate(scenario):
    r = measure_honesty(scenario, n_steps=50, seed=1, num_envs=6, world="mujoco")
    print(f"\nMuJoCo honesty {scenario}: rate={r['rate']:.4f} eligible={r['eligible']} "
          f"active={r['active']} row_rate={r['row_rate']} unsafe_by={r['unsafe_by']}")
    # the env hands out exactly the rows of its measured geometry
    assert r["rows_match"] == r["transitions"]
    assert r["eligible"] > 0 and r["active"] > 0
    assert r["rate"] >= 0.9
