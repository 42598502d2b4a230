"""The compiled step of BatchEnv (common/env/kernels.py) against its numpy references.

Every kernel equals its plain numpy reference (common/env/reference.py), on random
(hypothesis) and recorded states: the snapshot, observations and critic state, step outcome,
margin barrier, tracker targets, resets, episode placement, start clearance, observation
noise and episode sums. A whole BatchEnv rollout with every kernel swapped for its
reference gives the same outputs. The batched physics is checked too: wall contact from
``ncon`` and the floor sensor, the contact-filter guard, and the bench's raw-physics replay
reproducing the env's own physics steps.
"""
import mujoco
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from common.env import batch_env, observations, physics, reference, task
from common.env import safety as S
from common.env.batch_env import BatchEnv
from common.env.config import EnvConfig
from common.env.layout import FACING, GRASP_LOCAL, PAIR_REST, PAYLOAD_POINTS_LOCAL
from common.env.observations import OBS_DIM, STATE_DIM, Snapshot
from common.env.scenarios import SCENARIOS, Route

HYP = settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.too_slow])
K = 6


def _env(name="maze", k=K, seed=0, **kw):
    return BatchEnv(EnvConfig(name, **kw), num_envs=k, seed=seed)


def _recorded_envs(name, steps=(0, 3, 9, 20), seed=0, **kw):
    """A BatchEnv after each of ``steps`` random-action steps (with resets and drops on the way)."""
    env = _env(name, seed=seed, **kw)
    env.reset()
    rng = np.random.default_rng(seed)
    for t in range(max(steps) + 1):
        if t in steps:
            yield env
        env.step(np.clip(env.scripted_actions() + rng.normal(0.0, 0.6, (K, 9)), -1.0, 1.0))


def _random_state(env, rng, spread):
    """Put every env of ``env.phys`` at a random pose near its own route (after a reset, which draws
    every env's layout; formation jittered by ``spread`` m, random velocities and tilt), as state
    rows of the batch."""
    env.reset()
    phys, routes = env.phys, env.routes
    i = np.array([rng.integers(0, len(r.s)) for r in routes])
    xy = np.array([r.points[j] for r, j in zip(routes, i)]) + rng.normal(0.0, 0.5, (K, 2))
    yaw = np.array([r.heading[j] for r, j in zip(routes, i)]) + rng.normal(0.0, 0.5, K)
    carriers = np.empty((K, 3, 3))
    c, s = np.cos(yaw)[:, None], np.sin(yaw)[:, None]
    carriers[..., 0] = xy[:, None, 0] + c * GRASP_LOCAL[:, 0] - s * GRASP_LOCAL[:, 1]
    carriers[..., 1] = xy[:, None, 1] + s * GRASP_LOCAL[:, 0] + c * GRASP_LOCAL[:, 1]
    carriers[..., :2] += rng.normal(0.0, spread, (K, 3, 2))
    carriers[..., 2] = yaw[:, None] + FACING + rng.normal(0.0, 0.3, (K, 3))
    phys.reset(np.arange(K), xy, yaw, carriers)
    a = phys.payload_qadr
    quat = np.concatenate([np.cos(yaw / 2)[:, None], rng.normal(0.0, 0.05, (K, 2)), np.sin(yaw / 2)[:, None]], 1)
    phys.qpos[:, a + 2] += rng.normal(0.0, 0.05, K)
    phys.qpos[:, a + 3:a + 7] = quat / np.linalg.norm(quat, axis=1, keepdims=True)
    phys.qvel[:] = rng.normal(0.0, 0.3, phys.qvel.shape)
    phys.contact[:] = rng.random(K) < 0.5
    env.s_prev[:] = np.array([r.s[j] for r, j in zip(routes, i)]) + rng.normal(0.0, 0.3, K)
    env.goal_s[:] = rng.uniform(0.0, [r.length for r in routes])


def _assert_snapshots_equal(a: Snapshot, b: Snapshot):
    for name in Snapshot.__dataclass_fields__:
        x, y = getattr(a, name), getattr(b, name)
        if x.dtype == bool:
            np.testing.assert_array_equal(x, y, err_msg=name)
        else:
            np.testing.assert_allclose(x, y, rtol=0, atol=1e-12, err_msg=name)


def _check_snapshot_and_observe(env, rng, envs):
    """snapshot / observe of rows ``envs`` equal their references (other rows untouched)."""
    fast, ref = Snapshot.empty(K), Snapshot.empty(K)
    args = (env.phys, env.scene, env.s_prev, env.goal_s, env.cfg)
    observations.snapshot(*args, fast, envs)
    reference.snapshot(*args, ref, envs)
    _assert_snapshots_equal(fast, ref)
    goal_xy, goal_yaw = rng.uniform(-1.0, 11.0, (K, 2)), rng.uniform(-4.0, 4.0, K)
    progress, time_left = rng.random(K), rng.random(K)
    outs = []
    for fn in (observations.observe, reference.observe):
        obs, state = np.full((K, 3, OBS_DIM), 7.0, np.float32), np.full((K, STATE_DIM), 7.0, np.float32)
        fn(fast, env.scene, goal_xy, goal_yaw, progress, time_left, env.cfg, envs, obs, state)
        outs.append((obs, state))
    for a, b in zip(*outs):
        np.testing.assert_allclose(a, b, rtol=0, atol=1e-6)   # float32: one unit in the last place
    return fast


# ----------------------------------------------------------------------------- snapshot, observations

@HYP
@given(st.sampled_from(sorted(SCENARIOS)), st.integers(0, 2**31), st.floats(0.0, 0.3),
       st.sampled_from([None, 0, 2]))
@pytest.mark.sweep
def test_snapshot_and_observe_match_reference_on_random_states(name, seed, spread, human):
    rng = np.random.default_rng(seed)
    env = _env(name, human_slot=human)
    _random_state(env, rng, spread)
    _check_snapshot_and_observe(env, rng, np.arange(K))
    _check_snapshot_and_observe(env, rng, np.array([1, 4]))   # a subset, as for ended envs


@pytest.mark.parametrize("name,rows", [("maze", "paper"), ("needle_gate", "grasp")])
def test_kernels_match_reference_on_recorded_states(name, rows):
    rng = np.random.default_rng(1)
    for env in _recorded_envs(name, safety_rows=rows):
        snap = _check_snapshot_and_observe(env, rng, np.arange(K))
        geom = S.SafetyGeometry(snap.cxy, snap.cyaw, snap.pxy, snap.pyaw, PAYLOAD_POINTS_LOCAL, GRASP_LOCAL,
                                PAIR_REST)
        fast, ref = S.build_rows(geom, env.walls_array, env.safety_cfg), \
            reference.build_rows(geom, env.walls_array, env.safety_cfg)
        for a, b in zip(fast[:3], ref[:3]):
            np.testing.assert_allclose(a, b, rtol=0, atol=1e-12)
        for key in ("h", "entity", "wall"):
            np.testing.assert_allclose(fast[3][key], ref[3][key], rtol=0, atol=1e-12, err_msg=key)
        np.testing.assert_allclose(
            S.spec_barrier_min(snap.car_dist, snap.pay_dist, snap.cxy, PAIR_REST, env.safety_cfg),
            reference.spec_barrier_min(snap.car_dist, snap.pay_dist, snap.cxy, PAIR_REST, env.safety_cfg),
            rtol=0, atol=1e-12)


def test_grasp_strain_matches_reference():
    rng = np.random.default_rng(2)
    env = _env()
    _random_state(env, rng, 0.2)
    np.testing.assert_allclose(env.phys.grasp_strain(), reference.grasp_strain(env.phys), rtol=0, atol=1e-12)


# ----------------------------------------------------------------------------- outcome, margins, sums

def _random_snapshot(rng):
    snap = Snapshot.empty(K)
    for name in Snapshot.__dataclass_fields__:
        x = getattr(snap, name)
        if x.dtype == bool:
            x[:] = rng.random(x.shape) < 0.5
        else:
            x[:] = rng.normal(0.0, 1.0, x.shape)
    snap.strain[:] = rng.uniform(0.0, 0.3, snap.strain.shape)   # some above drop_strain
    snap.pyaw[:] = rng.uniform(-7.0, 7.0, K)
    return snap


@HYP
@given(st.integers(0, 2**31), st.integers(1, 400))
def test_step_outcome_matches_reference(seed, max_steps):
    rng = np.random.default_rng(seed)
    cfg = EnvConfig("maze", goal_pos_tol=1.5, goal_yaw_tol=2.0)   # wide: successes happen
    snap = _random_snapshot(rng)
    s_old = snap.s + rng.normal(0.0, 0.2, K)
    t = rng.integers(0, 2 * max_steps, K)
    goal_xy, goal_yaw = snap.pxy + rng.normal(0.0, 1.0, (K, 2)), rng.uniform(-4.0, 4.0, K)
    a = task.step_outcome(snap, s_old, t, max_steps, goal_xy, goal_yaw, cfg)
    b = reference.step_outcome(snap, s_old, t, max_steps, goal_xy, goal_yaw, cfg)
    for name in ("success", "drop", "terminated", "truncated", "collision"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name), err_msg=name)
    np.testing.assert_allclose(a.reward, b.reward, rtol=0, atol=1e-12)
    np.testing.assert_allclose(a.heading_error, b.heading_error, rtol=0, atol=1e-12)


@HYP
@given(st.integers(0, 2**31), st.sampled_from(["paper", "grasp"]), st.integers(0, 5))
def test_spec_barrier_min_matches_reference(seed, profile, P):
    rng = np.random.default_rng(seed)
    cfg = S.SafetyConfig(profile=profile)
    car, pay = rng.normal(0.5, 0.5, (K, 3)), rng.normal(0.5, 0.5, (K, P))
    cxy = GRASP_LOCAL[None] + rng.normal(0.0, 0.1, (K, 3, 2))
    want = reference.spec_barrier_min(car, pay, cxy, PAIR_REST, cfg)
    np.testing.assert_allclose(S.spec_barrier_min(car, pay, cxy, PAIR_REST, cfg), want, rtol=0, atol=1e-12)
    model = S.SafetyModel(SCENARIOS["maze"].walls_array(), cfg, K)   # the env's prepared path
    np.testing.assert_allclose(model.barrier_min(car, pay, cxy, PAIR_REST), want, rtol=0, atol=1e-12)


def test_episode_sums_match_reference():
    rng = np.random.default_rng(3)
    envs = [_env(), _env()]
    for env in envs:
        env.reset()
    for _ in range(3):
        snap = _random_snapshot(rng)
        o = reference.step_outcome(snap, snap.s, np.zeros(K, np.int64), 10, snap.pxy, snap.pyaw, envs[0].cfg)
        margin = rng.random(K) < 0.5
        for env, fn in zip(envs, (BatchEnv._accumulate, reference.accumulate)):
            env.snap = snap
            fn(env, o, margin)
    np.testing.assert_allclose(envs[0]._acc_all, envs[1]._acc_all, rtol=0, atol=1e-12)
    np.testing.assert_array_equal(envs[0]._min_clear, envs[1]._min_clear)


# ----------------------------------------------------------------------------- physics, episode starts

@HYP
@given(st.integers(0, 2**31))
@pytest.mark.sweep
def test_tracker_targets_and_reset_match_reference(seed):
    rng = np.random.default_rng(seed)
    fast, ref = _env(), _env()
    envs = np.sort(rng.choice(K, 3, replace=False))
    xy, yaw, pose = rng.uniform(0.0, 5.0, (3, 2)), rng.uniform(-4.0, 4.0, 3), rng.normal(0.0, 2.0, (3, 3, 3))
    fast.phys.reset(envs, xy, yaw, pose)
    reference.physics_reset(ref.phys, envs, xy, yaw, pose)
    np.testing.assert_allclose(fast.phys.batch.state, ref.phys.batch.state, rtol=0, atol=1e-15)
    qpos = rng.normal(0.0, 2.0, fast.phys.qpos.shape)
    ctrl = qpos[:, fast.phys.carrier_qadr.reshape(-1)] + rng.normal(0.0, 0.05, (K, 9))
    for phys in (fast.phys, ref.phys):
        phys.qpos[:], phys._ctrl[:] = qpos, ctrl
    actions = rng.uniform(-1.5, 1.5, (K, 9))   # beyond the box: the targets clip
    np.testing.assert_allclose(fast.phys.targets(actions), reference.physics_targets(ref.phys, actions),
                               rtol=0, atol=1e-12)


@HYP
@given(st.sampled_from(sorted(SCENARIOS)), st.integers(0, 2**31))
@pytest.mark.sweep
def test_episode_placement_and_start_clearance_match_reference(name, seed):
    rng = np.random.default_rng(seed)
    fast, ref = _env(name, seed=seed % 7), _env(name, seed=seed % 7)
    start = rng.normal(0.0, 1.0, (K, 3)) + [5.0, 0.0, 0.0]
    goal_s = rng.uniform(-1.0, Route(SCENARIOS[name].route).length + 1.0, K)
    envs = np.array([0, 2, 3])
    for env in (fast, ref):
        env.reset()   # every env in a layout of its own
        env._start[:], env.goal_s[:] = start, goal_s
    np.testing.assert_allclose(fast._place_episodes(envs), reference.place_episodes(ref, envs), rtol=0, atol=1e-12)
    np.testing.assert_allclose(fast.goal_xy, ref.goal_xy, rtol=0, atol=0)
    np.testing.assert_allclose(fast.goal_yaw, ref.goal_yaw, rtol=0, atol=0)
    for k, (x, y, yaw) in enumerate(start):
        assert fast.start_clearance((x, y), yaw, k) == pytest.approx(reference.start_clearance(ref, (x, y), yaw, k),
                                                                    abs=1e-12)


def test_observation_noise_matches_reference_across_refills():
    fast, ref = _env(), _env()
    for env in (fast, ref):
        env._noise_used[:] = env.NOISE_BLOCK
    for t in range(2 * BatchEnv.NOISE_BLOCK + 3):   # envs 1 and 4 draw twice as often
        envs = np.array([1, 4]) if t % 2 else np.arange(K)
        a, b = np.zeros((K, 3, OBS_DIM), np.float32), np.zeros((K, 3, OBS_DIM), np.float32)
        fast._add_noise(a, envs)
        reference.add_noise(ref, b, envs)
        np.testing.assert_array_equal(a, b)
    # the same stream as one draw per step: env 0's draws are its RNG's first normals
    env = _env()
    obs = np.zeros((K, 3, OBS_DIM), np.float32)
    env._add_noise(obs, np.arange(K))
    first = np.random.default_rng(np.random.SeedSequence(0).spawn(K)[0].spawn(1)[0]).standard_normal(
        (3, OBS_DIM), np.float32)
    np.testing.assert_array_equal(obs[0], first * env._obs_noise_std)


# ----------------------------------------------------------------------------- the whole env

class _ReferenceSafetyModel:
    """``safety.SafetyModel`` computed by ``reference.build_rows`` and ``reference.spec_barrier_min``."""

    def __init__(self, walls, cfg, num_envs):
        self.walls, self.cfg = np.array(walls, dtype=np.float64), cfg   # its own copy: set_walls must reach it

    def set_walls(self, k, walls):
        self.walls[k] = walls

    def rows(self, carrier_xy, carrier_yaw, payload_xy, payload_yaw, points, grasps, pair_rest):
        geom = S.SafetyGeometry(carrier_xy, carrier_yaw, payload_xy, payload_yaw, points, grasps, pair_rest)
        C, c, mask, info = reference.build_rows(geom, self.walls, self.cfg)
        return C, c, mask, info["h"], info["entity"], info["wall"]

    def barrier_min(self, carrier_sd, payload_sd, carrier_xy, pair_rest):
        return reference.spec_barrier_min(carrier_sd, payload_sd, carrier_xy, pair_rest, self.cfg)


def _use_references(monkeypatch):
    """Swap every kernel of BatchEnv's step for its numpy reference."""
    monkeypatch.setattr(observations, "snapshot", reference.snapshot)
    monkeypatch.setattr(observations, "observe", reference.observe)
    monkeypatch.setattr(task, "step_outcome", reference.step_outcome)
    monkeypatch.setattr(S, "SafetyModel", _ReferenceSafetyModel)
    monkeypatch.setattr(physics.TransportPhysics, "reset", reference.physics_reset)
    monkeypatch.setattr(physics.TransportPhysics, "targets", reference.physics_targets)
    monkeypatch.setattr(Route, "project", reference.route_project)
    monkeypatch.setattr(BatchEnv, "start_clearance", reference.start_clearance)
    monkeypatch.setattr(BatchEnv, "_place_episodes", reference.place_episodes)
    monkeypatch.setattr(BatchEnv, "_add_noise", reference.add_noise)
    monkeypatch.setattr(BatchEnv, "_accumulate", reference.accumulate)


@pytest.mark.parametrize("name,kw", [
    ("maze", {}),
    ("tilt_gate", {"human_slot": 1, "safety_rows": "grasp", "max_steps": 30}),
    ("chicane", {"start_spread": 2.0, "action_delay_steps": 1, "human_slot": 2, "max_steps": 15}),
])
@pytest.mark.sweep
def test_batch_env_matches_its_numpy_reference(name, kw, monkeypatch):
    """Same seed and actions: every output of every step equals the all-numpy env's, resets included."""
    cfg = EnvConfig(name, **kw)
    rng = np.random.default_rng(4)
    acts = rng.uniform(-1.0, 1.0, (60, K, 9))

    def run():
        env = batch_env.BatchEnv(cfg, num_envs=K, seed=5)
        outs = [env.reset()]
        for a in acts:
            outs.append(env.step(a))
            outs[-1]["qpos"] = env.phys.qpos.copy()
        return outs

    fast = run()
    _use_references(monkeypatch)
    ref = run()
    monkeypatch.undo()
    n_episodes = 0
    for a, b in zip(fast, ref):
        assert a.keys() == b.keys()
        for key in b:
            if key == "episodes":
                assert [e.keys() for e in a[key]] == [e.keys() for e in b[key]]
                for x, y in zip(a[key], b[key]):
                    for f in x:
                        want = y[f] if isinstance(y[f], str) else pytest.approx(y[f], rel=1e-9, abs=1e-9, nan_ok=True)
                        assert x[f] == want, f
                n_episodes += len(b[key])
            elif b[key].dtype == bool:
                np.testing.assert_array_equal(a[key], b[key], err_msg=key)
            else:
                atol = 1e-6 if b[key].dtype == np.float32 else 1e-9
                np.testing.assert_allclose(a[key], b[key], rtol=0, atol=atol, err_msg=key)
    assert n_episodes >= K   # resets (time limits and drops) were exercised


# ----------------------------------------------------------------------------- batched physics

def test_wall_contact_counts_every_contact_but_the_floors():
    """``ncon`` minus the floor sensor's count is the number of wall contacts (the contact filter
    lets nothing else collide), through a run that scrapes walls and drops the payload on the floor."""
    phys = physics.TransportPhysics(SCENARIOS["narrow_gate"], EnvConfig("narrow_gate"), 1)
    m = phys.model
    d = mujoco.MjData(m)
    pose = np.zeros((3, 3))
    pose[:, :2] = np.array([2.6, 0.4]) + GRASP_LOCAL
    pose[:, 2] = FACING
    a = phys.payload_qadr
    d.qpos[a:a + 7] = (2.6, 0.4, 0.8, 1.0, 0.0, 0.0, 0.0)
    d.qpos[phys.carrier_qadr.reshape(-1)] = d.ctrl[:] = pose.reshape(-1)
    rng = np.random.default_rng(0)
    seen = {"wall": 0, "floor": 0}
    for t in range(120):
        if t == 60:
            d.eq_active[:] = 0   # drop: the payload falls on the floor
        d.ctrl[:] = d.qpos[phys.carrier_qadr.reshape(-1)] + rng.normal([0.06, 0.0, 0.0] * 3, 0.05)
        mujoco.mj_step(m, d, 10)
        walls = sum(bool(phys.is_wall[d.contact.geom[i]].any()) for i in range(d.ncon))
        floors = sum(phys.floor_id in d.contact.geom[i] for i in range(d.ncon))
        assert walls + floors == d.ncon and floors == d.sensordata[0]
        seen["wall"] += walls > 0
        seen["floor"] += floors > 0
    assert seen["wall"] and seen["floor"]


def test_compile_model_refuses_a_contact_filter_the_count_cannot_read():
    xml = physics.build_mjcf(SCENARIOS["narrow_gate"], EnvConfig("narrow_gate"))
    # carriers that collide with the payload: contacts with neither a wall nor the floor
    bad = xml.replace('contype="0" conaffinity="2"', 'contype="1" conaffinity="2"').replace(
        'contype="0" conaffinity="6"', 'contype="0" conaffinity="7"')
    with pytest.raises(ValueError, match="may collide"):
        physics.compile_model(bad)


def test_datas_are_the_current_state_with_derived_fields():
    env = _env("narrow_gate", k=2, randomize=False)
    env.reset()
    for _ in range(3):
        env.step(np.zeros((2, 9)))
    d = env.phys.datas[1]
    np.testing.assert_array_equal(d.qpos, env.phys.qpos[1])
    np.testing.assert_array_equal(d.xpos[env.phys.payload_body, :2], env.phys.payload_pos[1, :2])
    assert len(env.phys.datas) == 2 and env.phys.datas[-1] is d


def test_bench_replay_steps_the_envs_own_physics():
    """The raw bound of `sage bench env` replays exactly the env's physics: from each recorded
    call, the rollout reaches the state the env reached (bitwise up to solver rounding)."""
    import mujoco.rollout

    from sage.bench.env import _record_physics_calls, _replay_inputs

    env = _env("maze", k=4)
    env.reset()
    calls = _record_physics_calls(env)
    rng = np.random.default_rng(0)
    after, reset = [], []
    for _ in range(12):
        out = env.step(rng.uniform(-1.0, 1.0, (4, 9)))
        after.append(env.phys.batch.state.copy())
        reset.append(out["terminated"] | out["truncated"])
    models, data, state0, warm0, control, spec = _replay_inputs(env.phys, calls)
    n_sub = env.cfg.substeps
    out = np.empty((len(models), n_sub, state0.shape[1]))
    with mujoco.rollout.Rollout(nthread=0) as raw:
        raw.rollout(models, [data], state0, control, control_spec=spec, skip_checks=True, nstep=n_sub,
                    initial_warmstart=warm0, state=out)
    full, integration = mujoco.mjtState.mjSTATE_FULLPHYSICS, mujoco.mjtState.mjSTATE_INTEGRATION
    probe, want = mujoco.MjData(env.phys.model), np.empty(state0.shape[1])
    checked = 0
    for t, rows in enumerate(after):
        for k in np.flatnonzero(~reset[t]):   # a reset env's state is no longer the physics' result
            mujoco.mj_setState(env.phys.model, probe, rows[k], integration)
            mujoco.mj_getState(env.phys.model, probe, want, full)
            np.testing.assert_allclose(out[t * 4 + k, -1], want, rtol=0, atol=1e-9)
            checked += 1
    assert checked >= 24
