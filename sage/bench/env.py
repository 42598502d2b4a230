"""`sage bench env` (env control steps/s vs the raw ``mujoco.rollout`` physics
bound of the same physics steps, measured in the same run) and `sage bench scripted`
(the scripted reference controller's success rate per scenario)."""
from __future__ import annotations

import json
import time

from common.env.batch_env import BatchEnv
from common.env.config import EnvConfig
from common.env.metrics import aggregate
from common.env.scenarios import SCENARIOS
from sage.bench.machine import machine
from sage.errors import nonneg_int, positive_int


def _record_physics_calls(env):
    """Wrap ``env.phys.batch.step`` to keep the state rows (mjSTATE_INTEGRATION: state, applied
    tracker targets, grasps, solver warm start), the payload masses and the walls (the envs' drawn
    layouts) each call starts from."""
    calls = []
    phys = env.phys
    step = phys.batch.step

    def recording_step(*args, **kwargs):
        calls.append((phys.batch.state.copy(), env.payload_mass.copy(), env.walls_array.copy()))
        return step(*args, **kwargs)

    phys.batch.step = recording_step
    return calls


def _replay_inputs(phys, calls):
    """mujoco.rollout inputs that replay the recorded physics calls: one rollout of ``substeps``
    steps per (control step, env) from its recorded state, with its applied controls held and
    its model (the MJCF's, without the env's contact sensors, at that env's payload mass and walls)."""
    import copy

    import mujoco
    import numpy as np

    from common.env.layout import PAYLOAD_MASS
    from common.env.physics import set_model_payload_mass, set_model_walls

    bare = mujoco.MjModel.from_xml_string(phys.xml)
    data = mujoco.MjData(bare)
    payload = mujoco.mj_name2id(bare, mujoco.mjtObj.mjOBJ_BODY, "payload")
    full, spec = mujoco.mjtState.mjSTATE_FULLPHYSICS, mujoco.mjtState.mjSTATE_INTEGRATION
    ctrl_spec = mujoco.mjtState.mjSTATE_CTRL | mujoco.mjtState.mjSTATE_EQ_ACTIVE
    n = len(calls) * phys.K
    state0 = np.empty((n, mujoco.mj_stateSize(bare, full)))
    warm0 = np.empty((n, bare.nv))
    control = np.empty((n, phys.cfg.substeps, mujoco.mj_stateSize(bare, ctrl_spec)))
    wall_ids = [np.array([mujoco.mj_name2id(bare, obj, f"wall{w}") for w in range(len(phys.nominal_walls))])
                for obj in (mujoco.mjtObj.mjOBJ_BODY, mujoco.mjtObj.mjOBJ_GEOM)]
    models, by_episode = [], {(PAYLOAD_MASS, phys.nominal_walls.tobytes()): bare}
    for t, (rows, masses, walls) in enumerate(calls):
        for k in range(phys.K):
            i = t * phys.K + k
            mujoco.mj_setState(bare, data, rows[k], spec)
            mujoco.mj_getState(bare, data, state0[i], full)
            warm0[i] = data.qacc_warmstart
            mujoco.mj_getState(bare, data, control[i, 0], ctrl_spec)
            control[i, 1:] = control[i, 0]
            key = (float(masses[k]), walls[k].tobytes())
            if key not in by_episode:
                by_episode[key] = m = copy.copy(bare)
                set_model_walls(m, walls[k], *wall_ids)
                set_model_payload_mass(m, bare, payload, key[0], data)
            models.append(by_episode[key])
    return models, data, state0, warm0, control, int(ctrl_spec)


def bench_env(scenario: str = "maze", num_envs: int = 16, steps: int = 100, seed: int = 0,
              repeats: int = 5) -> dict:
    """Control steps/s of BatchEnv (random actions, obs and safety rows included) vs the raw
    physics bound, ``ratio = env / raw`` (median over ``repeats`` rounds; the machine is shared,
    so absolute rates are noisy and the ratio of two back-to-back measurements is the figure).

    Each round times ``steps`` env control steps, then replays exactly those physics steps in C
    with ``mujoco.rollout``, one thread: every (control step, env) from the state it started from
    (qpos, qvel, solver warm start; after any episode reset), with the tracker targets and grasp
    flags it applied held for its ``substeps`` physics steps, on the MJCF's model at that env's
    payload mass and walls; inputs are built before timing and no outputs are recorded. Episode resets,
    observations, rows, the env's floor-contact sensor and the recording of the env's physics
    calls (a state-row copy per step) count as env time. A warm-up step before timing loads the
    numba kernels. ``ratio_cpu`` is the same ratio from this thread's CPU time (both parts run
    single-threaded in this thread), which is less sensitive to other processes on a loaded
    machine.
    """
    import statistics

    import mujoco.rollout
    import numpy as np

    if num_envs < 1 or steps < 1 or repeats < 1:
        raise ValueError("num_envs, steps and repeats must be >= 1")
    env = BatchEnv(EnvConfig(scenario), num_envs=num_envs, seed=seed)
    env.reset()
    rng = np.random.default_rng(seed)
    env.step(rng.uniform(-1.0, 1.0, (num_envs, 9)))  # warm-up (numba kernels, caches)
    calls = _record_physics_calls(env)
    n_sub = env.cfg.substeps
    rounds = []
    with mujoco.rollout.Rollout(nthread=0) as raw:
        for _ in range(repeats):
            acts = rng.uniform(-1.0, 1.0, (steps, num_envs, 9))
            calls.clear()
            t0, c0 = time.perf_counter(), time.thread_time()
            for t in range(steps):
                env.step(acts[t])
            t_env, c_env = time.perf_counter() - t0, time.thread_time() - c0
            models, data, state0, warm0, control, ctrl_spec = _replay_inputs(env.phys, calls)
            t0, c0 = time.perf_counter(), time.thread_time()
            raw.rollout(models, [data], state0, control, control_spec=ctrl_spec, skip_checks=True, nstep=n_sub,
                        initial_warmstart=warm0)
            t_raw, c_raw = time.perf_counter() - t0, time.thread_time() - c0
            rounds.append((steps * num_envs / t_env, steps * num_envs / t_raw, c_raw / c_env))
    env_sps = statistics.median(r[0] for r in rounds)
    raw_sps = statistics.median(r[1] for r in rounds)
    ratio = statistics.median(r[0] / r[1] for r in rounds)
    return {"scenario": scenario, "num_envs": num_envs, "control_steps": steps, "substeps": n_sub,
            "physics_steps_per_env": steps * n_sub, "repeats": repeats,
            "env_steps_per_s": env_sps, "raw_physics_env_steps_per_s": raw_sps, "ratio": ratio,
            "ratios": [r[0] / r[1] for r in rounds],
            "ratio_cpu": statistics.median(r[2] for r in rounds), "machine": machine()}


def bench_scripted(episodes: int = 20, scenarios=None, seed: int = 0, num_envs: int = 10) -> dict:
    """Success rate of the scripted reference controller per scenario (first `episodes` episodes;
    layouts drawn from the evaluation stream, EnvConfig's layout_spread)."""
    out = {}
    for name in scenarios or list(SCENARIOS):
        env = BatchEnv(EnvConfig(name), num_envs=min(num_envs, episodes), seed=seed, layout_purpose="eval")
        env.reset()
        eps = []
        while len(eps) < episodes:
            eps += env.step(env.scripted_actions())["episodes"]
        agg = aggregate(eps[:episodes])
        out[name] = {k: agg[k] for k in ("success_rate", "drop_rate", "col_per_1k", "completion_time",
                                         "min_clearance", "episodes")}
    out["mean_success_rate"] = sum(v["success_rate"] for k, v in out.items()) / len(out)
    return out


def _bench_env(args):
    res = bench_env(args.scenario, args.num_envs, args.steps, args.seed, args.repeats)
    if args.scripted:
        res["scripted"] = bench_scripted(args.episodes, seed=args.seed)
    print(json.dumps(res, indent=None if args.json else 2))


def _bench_scripted(args):
    res = bench_scripted(args.episodes, [args.scenario] if args.scenario else None, seed=args.seed)
    print(json.dumps(res, indent=None if args.json else 2))


def register(commands, bench) -> None:
    b = bench.add_parser("env", help="env control steps/s vs raw mujoco.rollout physics bound")
    b.add_argument("--json", action="store_true")
    b.add_argument("--scenario", choices=sorted(SCENARIOS), default="maze")
    b.add_argument("--num-envs", type=positive_int, default=16)
    b.add_argument("--steps", type=positive_int, default=100)
    b.add_argument("--seed", type=nonneg_int, default=0)
    b.add_argument("--repeats", type=positive_int, default=5, help="timed rounds; medians are reported")
    b.add_argument("--scripted", action="store_true", help="also report scripted success rates")
    b.add_argument("--episodes", type=positive_int, default=20)
    b.set_defaults(func=_bench_env)

    s = bench.add_parser("scripted", help="scripted reference controller success rate per scenario")
    s.add_argument("--json", action="store_true")
    s.add_argument("--episodes", type=positive_int, default=20)
    s.add_argument("--scenario", choices=sorted(SCENARIOS), default=None)
    s.add_argument("--seed", type=nonneg_int, default=0)
    s.set_defaults(func=_bench_scripted)
