"""Graded-outcome env fields (EnvConfig: start_spread, start_min_clearance, payload_mass_range,
obs_noise_xy/_yaw, action_delay_steps): each does what it says, seeded runs stay reproducible."""
import dataclasses

import mujoco
import numpy as np
import pytest

from common.env.batch_env import BatchEnv
from common.env.config import EnvConfig
from common.env.geometry import from_frame
from common.env.layout import PAYLOAD_MASS
from common.env.observations import OBS_FEATURE_NAMES, observation_noise_std
from common.env.scenarios import SCENARIOS

QUIET = dict(obs_noise_xy=0.0, obs_noise_yaw=0.0)


def _env(k=1, seed=0, **kw):
    kw.setdefault("scenario", "narrow_gate")
    return BatchEnv(EnvConfig(**kw), num_envs=k, seed=seed)


def _start_offsets(env):
    """Payload start pose of every env in its own route-start frame (its episode's layout): [K,3]
    (along, across, yaw)."""
    xy0 = np.array([r.points[0] for r in env.routes])
    yaw0 = np.array([r.heading[0] for r in env.routes])
    d = env.snap.pxy - xy0
    c, s = np.cos(yaw0), np.sin(yaw0)
    return np.stack([c * d[:, 0] + s * d[:, 1], -s * d[:, 0] + c * d[:, 1], env.snap.pyaw - yaw0], 1)


def test_defaults_and_validation():
    cfg = EnvConfig()
    assert cfg.start_spread == 1.5 and cfg.start_min_clearance == 0.1
    assert cfg.payload_mass_range == (9.0, 12.0)
    assert cfg.obs_noise_xy == 0.005 and cfg.obs_noise_yaw == 0.005 and cfg.action_delay_steps == 0
    for bad in (dict(start_spread=-1.0), dict(payload_mass_range=(0.0, 1.0)), dict(payload_mass_range=(12.0, 9.0)),
                dict(obs_noise_xy=-0.1), dict(action_delay_steps=-1)):
        with pytest.raises(ValueError):
            EnvConfig(**bad)


def test_randomize_false_is_fully_deterministic():
    """Nominal start, farthest goal, nominal mass, noise-free observations."""
    env = _env(k=3, seed=7, randomize=False)
    out = env.reset()
    np.testing.assert_allclose(_start_offsets(env), 0.0, atol=1e-9)
    assert np.all(env.payload_mass == PAYLOAD_MASS) and all(m is env.phys.model for m in env.phys.models)
    np.testing.assert_array_equal(out["obs"][0], out["obs"][1])
    quiet = _env(k=3, seed=8, randomize=False, **QUIET).reset()
    np.testing.assert_array_equal(out["obs"], quiet["obs"])


def test_original_start_box_is_reproduced_with_spread_one():
    """start_spread=1, no clearance test: the draws of the original randomization, bit for bit,
    around each env's own route start (the layouts have streams of their own)."""
    K, seed = 6, 3
    env = _env(k=K, seed=seed, start_spread=1.0, start_min_clearance=0.0)
    env.reset()
    spec = SCENARIOS["narrow_gate"]
    assert len({r.length for r in env.routes}) == K   # every env in a layout of its own
    for k, ss in enumerate(np.random.SeedSequence(seed).spawn(K)):
        route = env.routes[k]
        rng = np.random.default_rng(ss)
        off = rng.uniform(-1.0, 1.0, 3) * np.array(spec.start_range)
        yaw0 = float(route.heading[0])
        np.testing.assert_allclose(env.snap.pxy[k], route.points[0] + from_frame(off[:2], yaw0), atol=1e-9)
        goal_s = route.length - rng.uniform(0.0, spec.goal_range)
        assert env.goal_s[k] == goal_s


@pytest.mark.parametrize("name", ["narrow_gate", "tilt_gate", "chicane", "maze"])
@pytest.mark.sweep
def test_wider_spread_spreads_starts_and_keeps_them_clear(name):
    K = 200
    narrow = _env(k=K, seed=1, scenario=name, start_spread=1.0)
    wide = _env(k=K, seed=1, scenario=name, start_spread=2.0)
    narrow.reset(), wide.reset()
    box = np.array(SCENARIOS[name].start_range)
    off_n, off_w = np.abs(_start_offsets(narrow)), np.abs(_start_offsets(wide))
    assert np.all(off_n <= box + 1e-9) and np.all(off_w <= 2.0 * box + 1e-9)
    # wider on every axis (the clearance test trims the corners of the wide box a little)
    assert np.all(off_w.mean(0) > 1.5 * off_n.mean(0)), (off_n.mean(0), off_w.mean(0))
    assert np.all(off_w.max(0) > 1.0 * box)
    # collision-free: every start clears the walls by start_min_clearance, at the real reset state
    for env in (narrow, wide):
        assert env.snap.clearance.min() >= env.cfg.start_min_clearance - 1e-6
        assert not env.snap.contact.any()


def test_start_clearance_matches_the_snapshot():
    env = _env(k=20, seed=2, scenario="chicane", start_spread=2.0)
    env.reset()
    for k in range(env.K):
        assert env.start_clearance(env.snap.pxy[k], env.snap.pyaw[k], k) == pytest.approx(env.snap.clearance[k], abs=1e-6)


def test_payload_mass_is_drawn_per_episode_and_sets_the_weight():
    lo, hi = 9.0, 12.0
    env = _env(k=6, seed=4, payload_mass_range=(lo, hi), **QUIET)
    env.reset()
    m = env.payload_mass.copy()
    assert np.all((m >= lo) & (m <= hi)) and len(set(m)) == env.K
    for k in range(env.K):
        assert env.phys.payload_mass(k) == m[k]
        assert env.phys.models[k] is not env.phys.model
    assert env.phys.model.body_mass[env.phys.payload_body] == PAYLOAD_MASS   # the nominal model is untouched
    for _ in range(20):   # hold still: the grasps carry the payload's weight
        env.step(np.zeros((env.K, 9)))
    for k, d in enumerate(env.phys.datas):
        eq = d.efc_type == mujoco.mjtConstraint.mjCNSTR_EQUALITY
        lift = -d.efc_force[eq].reshape(-1, 3)[:, 2].sum()    # connect rows are world x, y, z
        assert lift == pytest.approx(m[k] * 9.81, rel=1e-3)
    # a new episode draws a new mass
    env2 = _env(k=1, seed=4, payload_mass_range=(lo, hi), max_steps=3)
    env2.reset()
    first = env2.payload_mass[0]
    for _ in range(3):
        out = env2.step(np.zeros((1, 9)))
    assert out["episodes"] and env2.payload_mass[0] != first and env2.phys.payload_mass(0) == env2.payload_mass[0]


def test_set_payload_mass_equals_compiling_the_model_with_that_mass():
    env = _env(k=1)
    env.phys.set_payload_mass(0, 11.5)
    xml = env.phys.xml.replace('size="0.8 0.4 0.02" mass="10"', 'size="0.8 0.4 0.02" mass="11.5"')
    assert xml != env.phys.xml
    ref, m = mujoco.MjModel.from_xml_string(xml), env.phys.models[0]
    for f in ("body_mass", "body_inertia", "body_subtreemass", "body_invweight0", "dof_invweight0", "dof_M0"):
        np.testing.assert_allclose(getattr(m, f), getattr(ref, f), rtol=1e-12, atol=1e-12, err_msg=f)
    assert m.stat.meaninertia == pytest.approx(ref.stat.meaninertia, rel=1e-12)
    assert m.stat.meanmass == pytest.approx(ref.stat.meanmass, rel=1e-12)
    env.phys.set_payload_mass(0, PAYLOAD_MASS)
    assert env.phys.models[0] is env.phys.model


def test_observation_noise_changes_obs_but_not_state_or_rows():
    K, seed = 32, 5
    noisy, clean = _env(k=K, seed=seed), _env(k=K, seed=seed, **QUIET)
    outs = [(noisy.reset(), clean.reset())]
    rng = np.random.default_rng(0)
    for _ in range(5):
        a = rng.uniform(-1, 1, (K, 9))
        outs.append((noisy.step(a), clean.step(a)))
    std = observation_noise_std(noisy.cfg)
    diffs = []
    for n, c in outs:
        for key in ("state", "C", "c", "row_mask", "fixed_mask", "progress"):
            np.testing.assert_array_equal(n[key], c[key], err_msg=key)
        for key in ("reward", "collision", "drop", "success"):
            if key in c:
                np.testing.assert_array_equal(n[key], c[key], err_msg=key)
        diffs.append((n["obs"] - c["obs"]).astype(np.float64).reshape(-1, len(OBS_FEATURE_NAMES)))
    np.testing.assert_array_equal(noisy.snap.pxy, clean.snap.pxy)   # same starts and physics
    d = np.concatenate(diffs)
    exact = std == 0
    assert {OBS_FEATURE_NAMES[i] for i in np.flatnonzero(exact)} == {"progress", "time_left"}
    assert np.all(np.abs(d[:, exact]) < 1e-6)
    # zero-mean Gaussian of the documented std (576 samples per feature)
    emp = d[:, ~exact].std(0)
    np.testing.assert_allclose(emp, std[~exact], rtol=0.15)
    assert np.all(np.abs(d[:, ~exact].mean(0)) < 4 * std[~exact] / np.sqrt(len(d)))
    # the slot feature's noise is a few mm in world units
    i = OBS_FEATURE_NAMES.index("slot_dx")
    assert 0.003 < std[i] * noisy.cfg.lookahead < 0.01


def test_action_delay_executes_the_previous_action():
    K = 2
    delayed = _env(k=K, seed=0, randomize=False, action_delay_steps=1, max_steps=6)
    direct = _env(k=K, seed=0, randomize=False, max_steps=6)
    delayed.reset(), direct.reset()
    rng = np.random.default_rng(1)
    acts = [rng.uniform(-1, 1, (K, 9)) for _ in range(5)]
    for t, a in enumerate(acts):
        previous = acts[t - 1] if t else np.zeros((K, 9))   # the delayed env executes zeros first
        delayed.step(a)
        np.testing.assert_array_equal(delayed.executed_action, previous)
        direct.step(previous)
        np.testing.assert_array_equal(delayed.phys.qpos, direct.phys.qpos)
    # episode end (max_steps=6): the queue restarts with zeros
    out = delayed.step(acts[0])
    assert len(out["episodes"]) == K
    delayed.step(acts[1])
    np.testing.assert_array_equal(delayed.executed_action, 0.0)


def test_action_delay_leaves_the_human_block_alone():
    env = _env(k=2, seed=3, human_slot=1, action_delay_steps=2)
    out = env.reset()
    rng = np.random.default_rng(2)
    for _ in range(4):
        human = out["human_action"].copy()
        out = env.step(rng.uniform(-1, 1, (2, 9)))
        np.testing.assert_array_equal(env.executed_action[:, 3:6], human[:, 3:6])


def test_seeded_runs_are_reproducible_with_every_field_on():
    cfg = dict(scenario="chicane", start_spread=2.0, action_delay_steps=1, human_slot=2, max_steps=12)

    def run(seed):
        env = _env(k=3, seed=seed, **cfg)
        out = env.reset()
        rng = np.random.default_rng(0)
        traj = [out["obs"], env.payload_mass.copy()]
        for _ in range(30):   # crosses two auto-resets
            out = env.step(np.clip(0.3 * rng.uniform(-1, 1, (3, 9)) + env.scripted_actions(), -1, 1))
            traj += [out["obs"], out["C"], out["reward"], out["final_obs"], env.payload_mass.copy(), env.phys.qpos.copy()]
        return traj

    a, b = run(11), run(11)
    for x, y in zip(a, b):
        np.testing.assert_array_equal(x, y)
    c = run(12)
    assert not np.array_equal(a[0], c[0]) and not np.array_equal(a[1], c[1])


def test_noise_settings_do_not_move_the_starts_or_masses():
    """Observation noise draws from its own stream: turning it off keeps the episode draws."""
    a, b = _env(k=4, seed=9), _env(k=4, seed=9, **QUIET)
    a.reset(), b.reset()
    np.testing.assert_array_equal(a.snap.pxy, b.snap.pxy)
    np.testing.assert_array_equal(a.payload_mass, b.payload_mass)
    np.testing.assert_array_equal(a.goal_s, b.goal_s)


def test_env_config_fields_survive_the_train_config_round_trip():
    """`--set env.payload_mass_range=[10,11]` and friends reach the env (tuple field from JSON)."""
    from sage.train import apply_override
    from services.config import TrainConfig

    cfg = TrainConfig()
    for item in ("env.payload_mass_range=[10.0, 11.0]", "env.action_delay_steps=1", "env.obs_noise_xy=0.01",
                 "env.start_spread=2.0"):
        apply_override(cfg, item)
    env_cfg = cfg.resolve().env_config()
    assert env_cfg.payload_mass_range == (10.0, 11.0) and env_cfg.action_delay_steps == 1
    assert env_cfg.obs_noise_xy == 0.01 and env_cfg.start_spread == 2.0
    assert dataclasses.replace(env_cfg).payload_mass_range == (10.0, 11.0)
