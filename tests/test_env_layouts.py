"""Scenarios as layout families (issue 29): the draw, the train/eval layout streams, one geometry
for physics, observations and shield, and solvability of drawn layouts by the scripted controller."""
import dataclasses
import re

import mujoco
import numpy as np
import pytest

from common.env import safety as S
from common.env.batch_env import BatchEnv
from common.env.config import EnvConfig
from common.env.geometry import wall_table
from common.env.layout import CARRIER_RADIUS
from common.env.mjcf import build_mjcf
from common.env.physics import compile_model, set_model_payload_mass
from common.env.scenarios import SCENARIOS, draw_layout
from common.env.scene import layout_rng


def _env(name="narrow_gate", k=4, seed=0, purpose="train", **kw):
    return BatchEnv(EnvConfig(name, **kw), num_envs=k, seed=seed, layout_purpose=purpose)


def _vector(layout):
    return np.array(list(layout.params.values()))


# ----------------------------------------------------------------------------- the draw

@pytest.mark.parametrize("name", list(SCENARIOS))
def test_draw_is_pure_bounded_and_nominal_at_spread_zero(name):
    spec = SCENARIOS[name]
    nominal = spec.nominal
    for rng in (None, np.random.default_rng(0)):
        z = draw_layout(spec, rng, 0.0)
        np.testing.assert_array_equal(z.walls, nominal.walls)
        np.testing.assert_array_equal(z.route, nominal.route)
    a = draw_layout(spec, np.random.default_rng(5), 1.0)
    b = draw_layout(spec, np.random.default_rng(5), 1.0)
    c = draw_layout(spec, np.random.default_rng(6), 1.0)
    np.testing.assert_array_equal(a.walls, b.walls)
    np.testing.assert_array_equal(a.route, b.route)
    assert not np.array_equal(a.walls, c.walls)
    half = np.array([p.half_range for p in spec.params])
    nom = np.array([p.nominal for p in spec.params])
    for spread in (0.5, 1.0):
        for seed in range(20):
            lay = draw_layout(spec, np.random.default_rng(seed), spread)
            assert np.all(np.abs(_vector(lay) - nom) <= spread * half + 1e-12)
            assert lay.walls.shape == nominal.walls.shape and lay.route.shape == nominal.route.shape
    with pytest.raises(ValueError):
        draw_layout(spec, np.random.default_rng(0), -0.1)


@pytest.mark.parametrize("name", list(SCENARIOS))
def test_every_spread_is_stated_in_the_scenario_docstring(name):
    spec = SCENARIOS[name]
    doc = spec.build.__doc__ or ""
    assert "Spreads" in doc or "spreads" in doc
    stated = {float(v) for v in re.findall(r"\+-(\d+(?:\.\d+)?)", doc)}
    for p in spec.params:
        assert p.half_range > 0 and p.unit in ("m", "deg")
        assert p.half_range in stated, f"{name}.{p.name}: +-{p.half_range:g} {p.unit} is not in the docstring"


def test_layout_spread_is_validated_and_zero_is_the_nominal_layout():
    for bad in (-0.5, float("nan"), 2.5):
        with pytest.raises(ValueError):
            EnvConfig(layout_spread=bad)
    with pytest.raises(ValueError):
        _env(purpose="test")
    env = _env("maze", k=3, layout_spread=0.0)
    env.reset()
    nominal = SCENARIOS["maze"].walls_array()
    for k in range(3):
        np.testing.assert_array_equal(env.walls_array[k], nominal)
        assert env.scene.layouts[k] is SCENARIOS["maze"].nominal
    off = _env("maze", k=3, randomize=False)   # randomize=False: nominal too
    off.reset()
    assert all(lay is SCENARIOS["maze"].nominal for lay in off.scene.layouts)
    on = _env("maze", k=3)
    on.reset()
    assert len({_vector(lay).tobytes() for lay in on.scene.layouts}) == 3   # default: spread on


# ----------------------------------------------------------------------------- streams

def test_train_and_eval_layout_streams_are_disjoint():
    """Evaluation layouts are held out: for the same integer seeds (a training seed may equal an
    evaluation seed, e.g. actor seeds 1000*s+a and FINAL_EVAL_SEED+s), the train and eval streams
    share no layout, and every episode of every env draws a fresh one."""
    spec = SCENARIOS["double_gate"]
    draws = {}
    for purpose in ("train", "eval"):
        draws[purpose] = {_vector(draw_layout(spec, layout_rng(seed, purpose, k, e))).tobytes()
                          for seed in (0, 1, 10_000) for k in range(8) for e in range(6)}
        assert len(draws[purpose]) == 3 * 8 * 6   # no layout repeats within a stream either
    assert not draws["train"] & draws["eval"]


def test_layouts_follow_purpose_seed_env_and_episode_only():
    """Env k's e-th episode runs in draw_layout(spec, layout_rng(seed, purpose, k, e)), whatever the
    other settings (start spread, noise, mass) draw; evaluation envs use the eval stream."""
    spec = SCENARIOS["narrow_gate"]
    a = _env(k=3, seed=4, max_steps=5)
    b = _env(k=3, seed=4, max_steps=5, start_spread=2.0, obs_noise_xy=0.0, payload_mass_range=(10.0, 10.0))
    ev = _env(k=3, seed=4, max_steps=5, purpose="eval")
    for env in (a, b, ev):
        env.reset()
    for episode in range(3):   # episodes end at the 5-step limit; auto-reset draws the next layout
        for k in range(3):
            want = draw_layout(spec, layout_rng(4, "train", k, episode))
            for env in (a, b):
                np.testing.assert_array_equal(env.walls_array[k], want.walls)
                np.testing.assert_array_equal(env.routes[k].points[0], want.route[0])
            np.testing.assert_array_equal(ev.walls_array[k], draw_layout(spec, layout_rng(4, "eval", k, episode)).walls)
        for env in (a, b, ev):
            for _ in range(5):
                env.step(np.zeros((3, 9)))


def test_evaluation_draws_from_the_eval_stream(monkeypatch):
    from common.evaluation import deployment

    seen = []

    class Spy(BatchEnv):
        def __init__(self, *args, **kwargs):
            super().__init__(*args, **kwargs)
            seen.append(self.layout_purpose)
            raise RuntimeError("stop")

    monkeypatch.setattr(deployment, "BatchEnv", Spy)
    monkeypatch.setattr(deployment, "ValidatedParams", lambda params: params)
    with pytest.raises(RuntimeError, match="stop"):
        deployment.evaluate_policy({}, EnvConfig(), 1, seed=0, shielded=True)
    assert seen == ["eval"]


# ----------------------------------------------------------------------------- one geometry

def _array_fields(m):
    for name in dir(m):
        if name.startswith("_"):
            continue
        try:
            v = getattr(m, name)
        except Exception:
            continue
        if isinstance(v, np.ndarray):
            yield name, v


@pytest.mark.parametrize("name", ["tilt_gate", "chicane", "l_corridor"])
def test_each_envs_model_is_the_model_compiled_with_its_layout(name):
    """No recompilation per episode: env k's model (nominal model with its walls moved and resized,
    payload mass set) equals, array by array, the MJCF compiled with that layout and mass."""
    env = _env(name, k=3, seed=2)
    env.reset()
    for k in range(3):
        assert not np.array_equal(env.walls_array[k], SCENARIOS[name].walls_array())
        want = compile_model(build_mjcf(env.spec, env.cfg, walls=env.walls_array[k]))
        set_model_payload_mass(want, compile_model(env.phys.xml), env.phys.payload_body, float(env.payload_mass[k]),
                               mujoco.MjData(want))
        got = env.phys.models[k]
        for field, arr in _array_fields(want):
            np.testing.assert_allclose(getattr(got, field), arr, rtol=0, atol=1e-12, err_msg=field)


def _mujoco_boxes(env, k):
    """Env k's wall boxes (cx, cy, hx, hy, yaw) as MuJoCo places them (world geom pose and size)."""
    d, m = env.phys.datas[k], env.phys.models[k]
    g = env.phys.wall_geoms
    xmat = d.geom_xmat[g].reshape(-1, 3, 3)
    return np.stack([d.geom_xpos[g, 0], d.geom_xpos[g, 1], m.geom_size[g, 0], m.geom_size[g, 1],
                     np.arctan2(xmat[:, 1, 0], xmat[:, 0, 0])], axis=1)


@pytest.mark.parametrize("name", ["needle_gate", "double_gate", "s_corridor"])
def test_shield_observations_and_physics_see_the_same_walls(name):
    """The walls the safety rows use (SafetyModel tables), the observations and clearance use
    (scene tables) and MuJoCo collides with are one layout, env by env and episode by episode;
    and the carrier-wall distance MuJoCo computes is the rows' barrier geometry."""
    env = _env(name, k=3, seed=3, max_steps=4)
    env.reset()
    moved = 0.0
    for episode in range(2):
        for k in range(3):
            walls = env.walls_array[k]
            boxes = _mujoco_boxes(env, k)
            np.testing.assert_allclose(boxes[:, :4], walls[:, :4], rtol=0, atol=1e-9)
            np.testing.assert_allclose(np.exp(1j * boxes[:, 4]), np.exp(1j * walls[:, 4]), rtol=0, atol=1e-9)
            np.testing.assert_array_equal(env._safety_model.tables[k], wall_table(walls))
            np.testing.assert_array_equal(env.scene.tables[k], wall_table(walls))
            # MuJoCo's distance from each carrier disc to each wall vs the safety model's box distance
            d, m = env.phys.datas[k], env.phys.models[k]
            cxy = env.snap.cxy[k]
            sd = S.point_box_distance(cxy[None], walls[None])[0][0]                  # [3,W]
            sd_nominal = S.point_box_distance(cxy[None], env.spec.walls_array()[None])[0][0]
            for i in range(3):
                gi = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_GEOM, f"carrier{i}")
                for w, gw in enumerate(env.phys.wall_geoms):
                    if sd[i, w] - CARRIER_RADIUS > 1.5:
                        continue
                    dist = mujoco.mj_geomDistance(m, d, gi, int(gw), 2.0, None)
                    assert dist == pytest.approx(sd[i, w] - CARRIER_RADIUS, abs=1e-4), (k, i, w)
                    moved = max(moved, abs(sd[i, w] - sd_nominal[i, w]))
        for _ in range(4):
            env.step(np.zeros((3, 9)))
    assert moved > 0.02   # the layouts moved the walls the check looked at


def test_safety_model_set_walls_refuses_a_shared_table():
    cfg = S.SafetyConfig()
    shared = S.SafetyModel(SCENARIOS["maze"].walls_array(), cfg, 2)
    with pytest.raises(ValueError):
        shared.set_walls(0, SCENARIOS["maze"].walls_array())
    per_env = S.SafetyModel(np.repeat(SCENARIOS["maze"].walls_array()[None], 2, 0), cfg, 2)
    with pytest.raises(ValueError):
        per_env.set_walls(0, SCENARIOS["maze"].walls_array()[:3])


def test_physics_refuses_a_layout_with_another_wall_count():
    env = _env("maze", k=1)
    with pytest.raises(ValueError):
        env.phys.set_walls(0, SCENARIOS["maze"].walls_array()[:-1])
    with pytest.raises(ValueError):
        env.scene.set(0, dataclasses.replace(SCENARIOS["maze"].nominal, walls=SCENARIOS["maze"].walls_array()[:-1]))


# ----------------------------------------------------------------------------- solvability

def _scripted_episodes(name, n, seed, purpose="eval"):
    env = _env(name, k=n, seed=seed, purpose=purpose)
    env.reset()
    done = [None] * n
    while any(e is None for e in done):
        out = env.step(env.scripted_actions())
        for k, ep in zip(np.flatnonzero(out["terminated"] | out["truncated"]), out["episodes"]):
            if done[k] is None:
                done[k] = ep
    return done


@pytest.mark.parametrize("name", list(SCENARIOS))
def test_clean_scripted_controller_solves_drawn_layouts(name):
    """Solvable: the clean (unshielded, noise-free) scripted controller reaches the goal without a
    drop. It follows its route blind to the walls, so in the narrowest drawn chicane lanes it may
    graze a wall for a few steps (docs/protocol/calibration.md counts it); the nominal layouts stay
    contact-free (tests/test_env.py)."""
    eps = _scripted_episodes(name, 3, seed=21)
    assert all(e["success"] and not e["drop"] for e in eps), eps


@pytest.mark.slow
@pytest.mark.parametrize("name", list(SCENARIOS))
def test_clean_scripted_controller_solves_many_drawn_layouts(name):
    eps = _scripted_episodes(name, 16, seed=22, purpose="train")
    assert all(e["success"] and not e["drop"] for e in eps), [e for e in eps if not e["success"]]


# ----------------------------------------------------------------------------- calibration, render

def test_calibration_arms_report_separate_outcomes_and_the_shield(capsys):
    """The calibration's four arms on a few held-out episodes: outcomes partition the episodes,
    the shield's figures exist exactly for the shielded arms, the bias changes the outcome, and
    the CLI prints one row per arm."""
    from common.evaluation.calibration import ARMS, run_arm
    from sage.cli import main

    cfg = EnvConfig("narrow_gate")
    res = {arm: run_arm(cfg, 4, seed=1, arm=arm) for arm in ARMS}
    for arm, r in res.items():
        assert r["episodes"] == 4
        assert r["success_rate"] + r["drop_rate"] + r["truncation_rate"] == pytest.approx(1.0)
        assert (r["intervention_rate"] is None) == (not arm.endswith("+shield"))
    assert res["clean"]["success_rate"] == 1.0 and res["clean+shield"]["infeasible_steps"] == 0
    assert res["biased"]["collision_episode_rate"] > 0   # aimed 0.2 m off the route it scrapes unshielded
    assert res["biased+shield"]["col_per_1k_pooled"] == 0 and res["biased+shield"]["intervention_rate"] > 0
    with pytest.raises(ValueError):
        run_arm(cfg, 1, seed=0, arm="noisy")
    assert main(["env", "calibrate", "--scenario", "narrow_gate", "--episodes", "2"]) == 0
    rows = [line for line in capsys.readouterr().out.splitlines() if line.startswith("| narrow_gate")]
    assert [r.split("|")[2].strip() for r in rows] == list(ARMS)


def test_render_overlays_drawn_layouts(tmp_path):
    from common.env.render import drawn_layouts, render

    lays = drawn_layouts("maze", 4, seed=3)
    assert len({_vector(lay).tobytes() for lay in lays}) == 4
    rec = render(str(tmp_path / "m.png"), ["maze"], seed=3, layouts=4)
    assert rec["maze"]["success"] and (tmp_path / "m.png").stat().st_size > 1000
