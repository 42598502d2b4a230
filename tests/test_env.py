"""MuJoCo three-carrier transport environment (issue 3)."""
from __future__ import annotations

import math
import sys
import types

import mujoco
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from common.env.config import EnvConfig
from common.env.geometry import WallSet
from common.env.layout import FACING, GRASP_LOCAL
from common.env.scenarios import FAMILIES, SCENARIO_TITLES, SCENARIOS, Route, formation_footprint


@pytest.fixture(autouse=True, scope="module")
def safety_module():
    """Use the real common.env.safety if present; else a minimal fake of its contract."""
    try:
        import common.env.safety  # noqa: F401
        yield
        return
    except ImportError:
        pass
    from dataclasses import dataclass

    fake = types.ModuleType("common.env.safety")

    @dataclass
    class SafetyConfig:
        alpha: float = 0.2
        max_rows: int = 34
        carrier_radius: float = 0.3
        max_step_xy: float = 0.05
        max_step_yaw: float = 0.1

    @dataclass
    class SafetyGeometry:
        carrier_xy: np.ndarray
        carrier_yaw: np.ndarray
        payload_xy: np.ndarray
        payload_yaw: np.ndarray
        payload_points_local: np.ndarray
        grasp_local: np.ndarray
        pair_rest: np.ndarray

    def build_rows(geom, walls, cfg):
        K = geom.carrier_xy.shape[0]
        return np.zeros((K, cfg.max_rows, 9)), np.zeros((K, cfg.max_rows)), np.zeros((K, cfg.max_rows), bool), {}

    fake.SafetyConfig, fake.SafetyGeometry, fake.build_rows = SafetyConfig, SafetyGeometry, build_rows
    sys.modules["common.env.safety"] = fake
    yield
    del sys.modules["common.env.safety"]


def _env(name="narrow_gate", k=1, seed=0, **kw):
    from common.env.batch_env import BatchEnv

    return BatchEnv(EnvConfig(name, **kw), num_envs=k, seed=seed)


def test_registry_and_config_validation():
    assert len(SCENARIOS) == 9 and sum(len(v) for v in FAMILIES.values()) == 9
    assert set(SCENARIO_TITLES) == set(SCENARIOS)
    with pytest.raises(ValueError):
        EnvConfig("no_such_scenario")
    with pytest.raises(ValueError):
        EnvConfig(human_slot=3)


@pytest.mark.parametrize("name", list(SCENARIOS))
def test_scenario_builds_and_mjcf_walls_match_spec(name):
    from common.env.physics import TransportPhysics

    phys = TransportPhysics(SCENARIOS[name], EnvConfig(name), 1)
    m, d = phys.model, phys.datas[0]
    mujoco.mj_forward(m, d)
    walls = SCENARIOS[name].walls_array()
    ids = np.flatnonzero(phys.is_wall)
    assert len(ids) == len(walls)
    for g, (cx, cy, hx, hy, yaw) in zip(ids, walls):
        np.testing.assert_allclose(d.geom_xpos[g, :2], [cx, cy], atol=1e-9)
        np.testing.assert_allclose(m.geom_size[g, :2], [hx, hy], atol=1e-9)
        R = d.geom_xmat[g].reshape(3, 3)
        np.testing.assert_allclose(R[:2, 0], [math.cos(yaw), math.sin(yaw)], atol=1e-7)
    # the reference route is collision-free for the rigid formation footprint
    route = Route(SCENARIOS[name].route)
    clr = WallSet(walls).signed_distance(formation_footprint(route.points, route.heading)).min()
    assert clr > 0.05


@given(st.floats(-3, 3), st.floats(-3, 3), st.floats(0.05, 1.5), st.floats(0.05, 1.5), st.floats(-3.2, 3.2),
       st.floats(-5, 5), st.floats(-5, 5))
@settings(max_examples=60, deadline=None)
def test_box_distance_matches_mujoco_sampling(cx, cy, hx, hy, yaw, px, py):
    ws = WallSet(np.array([[cx, cy, hx, hy, yaw]]))
    d = ws.signed_distance(np.array([px, py]))[0]
    # independent reference: distance to a dense sampling of the box boundary, sign from containment
    t = np.linspace(-1, 1, 801)
    loc = np.concatenate([np.stack([t * hx, np.full_like(t, s * hy)], 1) for s in (-1, 1)]
                         + [np.stack([np.full_like(t, s * hx), t * hy], 1) for s in (-1, 1)])
    c, s = math.cos(yaw), math.sin(yaw)
    world = loc @ np.array([[c, s], [-s, c]]) + [cx, cy]
    ref = np.min(np.linalg.norm(world - [px, py], axis=1))
    q = np.array([[c, s], [-s, c]]) @ np.array([px - cx, py - cy])
    inside = abs(q[0]) < hx and abs(q[1]) < hy
    assert abs(abs(d) - ref) < 2 * max(hx, hy) / 800 + 1e-9
    assert (d < 0) == inside or abs(d) < 1e-9
    # ray along -q direction toward the box centre hits at the boundary distance when outside
    if not inside and d > 1e-3:
        direc = np.array([cx - px, cy - py])
        direc /= np.linalg.norm(direc)
        r = ws.ray_distance(np.array([px, py]), direc, 100.0)
        assert r >= d - 1e-9


@pytest.mark.parametrize("name", list(SCENARIOS))
def test_scripted_controller_solves_scenario(name):
    env = _env(name, k=2, seed=11)
    env.reset()
    eps = []
    while len(eps) < 2:
        eps += env.step(env.scripted_actions())["episodes"]
    assert all(e["success"] and not e["drop"] for e in eps[:2]), eps
    assert all(e["collision_steps"] == 0 for e in eps[:2])


def test_observation_layout_and_scaling():
    from common.env.observations import OBS_FEATURE_NAMES

    env = _env("maze", k=3, obs_noise_xy=0.0, obs_noise_yaw=0.0)   # the noise-free geometry of the features
    out = env.reset()
    assert out["obs"].shape == (3, 3, len(OBS_FEATURE_NAMES)) and out["obs"].dtype == np.float32
    assert len(set(OBS_FEATURE_NAMES)) == len(OBS_FEATURE_NAMES)
    for _ in range(20):
        out = env.step(env.scripted_actions())
        assert np.all(np.abs(out["obs"]) < 5.0) and np.all(np.abs(out["state"]) < 10.0)
    # slot vector: rotating the carrier-frame vector back to world gives slot - carrier position
    from common.env.observations import slot_targets

    o = out["obs"]
    slot, _ = slot_targets(env.snap)
    i = OBS_FEATURE_NAMES.index("slot_dx")
    vec = o[..., i:i + 2].astype(np.float64) * env.cfg.lookahead
    c, s = np.cos(env.snap.cyaw), np.sin(env.snap.cyaw)
    world = np.stack([c * vec[..., 0] - s * vec[..., 1], s * vec[..., 0] + c * vec[..., 1]], -1)
    np.testing.assert_allclose(world, slot - env.snap.cxy, atol=1e-5)
    assert out["C"].shape == (3, env.max_rows, 9) and out["row_mask"].dtype == bool


def test_determinism_same_seed_same_trajectory():
    runs = []
    for _ in range(2):
        env = _env("chicane", k=2, seed=5)
        out = env.reset()
        rng = np.random.default_rng(0)
        traj = [out["obs"].copy()]
        for _ in range(30):
            a = 0.3 * rng.uniform(-1, 1, (2, 9)) + env.scripted_actions()
            out = env.step(np.clip(a, -1, 1))
            traj += [out["obs"].copy(), out["reward"].copy(), out["C"].copy()]
        runs.append(traj)
    for a, b in zip(*runs):
        np.testing.assert_array_equal(a, b)
    other = _env("chicane", k=2, seed=6).reset()["obs"]
    assert not np.array_equal(other, runs[0][0])


def test_careless_formation_change_drops_payload():
    env = _env("narrow_gate", k=1, randomize=False)
    env.reset()
    z0 = env.snap.pz[0]
    a = np.zeros((1, 9))
    a[0, 0] = -1.0  # carrier 0 (front, facing back) walks away from the payload alone
    for t in range(30):
        out = env.step(a)
        if out["terminated"][0]:
            break
    assert out["drop"][0] and out["terminated"][0] and not out["truncated"][0]
    assert out["episodes"][0]["drop"] and out["reward"][0] < -5
    # physics: the grasp really released; stepping on lets the payload fall to the floor
    phys = env.phys
    from common.env.physics import TransportPhysics

    ph = TransportPhysics(env.spec, env.cfg, 1)
    pose = np.zeros((3, 3))
    pose[:, :2] = np.array([2.0, 0.1]) + GRASP_LOCAL
    pose[:, 2] = FACING
    ph.reset(0, (2.0, 0.1), 0.0, pose)
    ph.release(0)
    assert not ph.datas[0].eq_active.any()
    for _ in range(10):
        ph.step(np.zeros((1, 9)))
    assert ph.payload_pos[0, 2] < 0.1 < z0
    assert phys is not None


def test_collision_detected_when_driving_into_wall():
    env = _env("narrow_gate", k=1, randomize=False)
    env.reset()
    # every carrier drives toward world -y (side wall at y = -1.5) in its own frame
    a = np.zeros((1, 9))
    for i in range(3):
        ang = -math.pi / 2 - FACING[i]
        a[0, 3 * i:3 * i + 2] = [math.cos(ang), math.sin(ang)]
    hit = False
    for _ in range(25):
        out = env.step(a)
        hit |= bool(out["collision"][0])
        if hit:
            break
    assert hit
    assert env.snap.clearance[0] < 0.02


def test_truncation_vs_termination():
    env = _env("maze", k=2, max_steps=5)
    env.reset()
    for t in range(5):
        out = env.step(np.zeros((2, 9)))
    assert out["truncated"].all() and not out["terminated"].any()
    assert len(out["episodes"]) == 2 and not out["episodes"][0]["success"]
    from common.env.observations import OBS_FEATURE_NAMES

    # final_obs is the pre-reset observation (no time left); obs is after the auto-reset
    assert np.allclose(out["final_obs"][..., OBS_FEATURE_NAMES.index("time_left")], 0.0)
    assert np.all(np.any(out["final_state"] != 0, axis=1))

    assert np.allclose(out["obs"][..., OBS_FEATURE_NAMES.index("time_left")], 1.0)


def test_success_terminates():
    env = _env("narrow_gate", k=1, seed=2)
    env.reset()
    for _ in range(300):
        out = env.step(env.scripted_actions())
        if out["episodes"]:
            break
    assert out["success"][0] and out["terminated"][0] and not out["truncated"][0]
    assert out["reward"][0] > 5


def test_human_slot_fixed_mask_and_override():
    env = _env("l_corridor", k=2, seed=1, human_slot=1)
    out = env.reset()
    fm = out["fixed_mask"]
    assert fm[:, 3:6].all() and not fm[:, :3].any() and not fm[:, 6:].any()
    h = out["human_action"][:, 3:6].copy()
    assert np.all(np.abs(h) <= 1) and np.any(h != 0)
    assert np.all(out["human_action"][:, :3] == 0)
    # whatever the caller sends for the human block, the human's reported action is executed
    pose0 = env.phys.carrier_pose.copy()
    a = np.zeros((2, 9))
    a[:, 3:6] = -np.sign(h) * 1.0
    env.step(a)
    targets = env.phys._ctrl.reshape(2, 3, 3)[:, 1]
    yaw = pose0[:, 1, 2]
    expect_xy = pose0[:, 1, :2] + 0.08 * np.stack([np.cos(yaw) * h[:, 0] - np.sin(yaw) * h[:, 1],
                                                    np.sin(yaw) * h[:, 0] + np.cos(yaw) * h[:, 1]], -1)
    np.testing.assert_allclose(targets[:, :2], expect_xy, atol=1e-9)


def test_pettingzoo_parallel_api():
    from pettingzoo.test import parallel_api_test

    from common.env.parallel_env import TransportParallelEnv

    env = TransportParallelEnv(EnvConfig("narrow_gate", max_steps=30), seed=3)
    assert env.observation_space("carrier_0") is env.observation_space("carrier_0")
    assert env.action_space("carrier_1") is env.action_space("carrier_1")
    parallel_api_test(env, num_cycles=60)


def test_bad_actions_rejected():
    env = _env()
    env.reset()
    with pytest.raises(ValueError):
        env.step(np.zeros((1, 8)))
    with pytest.raises(ValueError):
        env.step(np.full((1, 9), np.nan))


def test_metrics_aggregate():
    from common.env.metrics import aggregate

    eps = [dict(success=True, drop=False, **{"return": 3.0}, steps=100, collision_steps=2, col_per_1k=20.0,
                completion_time=10.0, tilt=1.0, heading_error=0.1, height_error=0.01, min_clearance=0.2,
                progress_per_step=0.01, final_progress=1.0),
           dict(success=False, drop=True, **{"return": -7.0}, steps=50, collision_steps=0, col_per_1k=0.0,
                completion_time=float("nan"), tilt=3.0, heading_error=0.3, height_error=0.03, min_clearance=0.1,
                progress_per_step=0.004, final_progress=0.2)]
    agg = aggregate(eps)
    assert agg["success_rate"] == 0.5 and agg["drop_rate"] == 0.5 and agg["return_mean"] == -2.0
    assert agg["col_per_1k"] == 10.0 and agg["col_per_1k_pooled"] == pytest.approx(1000 * 2 / 150)
    assert agg["completion_time"] == 10.0 and agg["return_mean_std"] == 5.0
    assert math.isnan(aggregate([])["success_rate"])


def test_cli_registers_and_bench_runs(tmp_path, capsys):
    import json

    from sage.bench.env import bench_env
    from sage.cli import main

    res = bench_env("narrow_gate", num_envs=2, steps=5)
    assert {"env_steps_per_s", "raw_physics_env_steps_per_s", "ratio"} <= set(res) and res["ratio"] > 0
    out = tmp_path / "g.png"
    assert main(["env", "render", "--scenario", "narrow_gate", "--out", str(out)]) == 0
    assert out.stat().st_size > 1000
    assert main(["bench", "scripted", "--json", "--episodes", "1", "--scenario", "narrow_gate"]) == 0
    line = capsys.readouterr().out.strip().splitlines()[-1]
    assert json.loads(line)["narrow_gate"]["success_rate"] == 1.0
