"""K transport environments in one process (one MjModel, K simulations): the actors' env API.

The batch bookkeeping lives here: the per-episode layout draw (each env runs its
episode in its own layout of the scenario, ``common/env/scene.py``), start/goal randomization, the graded-outcome
variation (wider starts, payload mass, observation noise, actuation delay; see
EnvConfig), the scripted human slot, auto-reset, safety rows for the next action
and per-episode metrics.
Physics is ``physics.py``; what a step means for the task (reward, success,
drop, termination vs truncation) is ``task.py``. See docs/interfaces.md
(common/env) for the dict returned by ``reset``/``step``.

A step is vectorized over the K envs: one batched physics call, then one kernel
call each for the snapshot, the outcome, the observations and the safety rows
(common/env/kernels.py), so per-env Python is left only where an env's own
random streams are drawn (episode starts, observation noise, the human).
The kernels are reached through their modules (``observations.snapshot``,
``task.step_outcome``, ...), which the tests swap for the numpy references (common/env/reference.py).
"""
from __future__ import annotations

import numpy as np

from common.env import kernels, observations, task
from common.env.config import EnvConfig
from common.env.metrics import margin_violation
from common.env.layout import (CARRIER_RADIUS, CARRY_HEIGHT, FACING, GRASP_LOCAL, PAIR_REST, PAYLOAD_MASS,
                               PAYLOAD_POINTS_LOCAL)
from common.env.observations import OBS_DIM, STATE_DIM, Snapshot, observation_noise_std
from common.env.physics import TransportPhysics
from common.env.scenarios import SCENARIOS, draw_layout
from common.env.scene import PURPOSES, SceneBatch, layout_rng
from common.env.scripted import ScriptedHuman, scripted_actions
from common.spec import CARRIER_ACT_DIM, JOINT_ACT_DIM, N_CARRIERS


def safety_config(cfg: EnvConfig):
    from common.env import safety  # resolved at call time: tests swap in a fake safety module

    return safety.SafetyConfig(alpha=cfg.alpha, max_rows=cfg.max_rows, carrier_radius=CARRIER_RADIUS + 0.05,
                               max_step_xy=cfg.max_step_xy, max_step_yaw=cfg.max_step_yaw, grasp_tol=cfg.grasp_tol,
                               profile=cfg.safety_rows)


class BatchEnv:
    n_agents = N_CARRIERS
    act_dim = CARRIER_ACT_DIM
    obs_dim = OBS_DIM
    state_dim = STATE_DIM

    def __init__(self, cfg: EnvConfig, num_envs: int = 1, seed=0, layout_purpose: str = "train"):
        """``layout_purpose``: ``"train"`` or ``"eval"``, the layout stream its episodes draw from
        (common/env/scene.py: evaluation runs on layouts training never draws)."""
        from common.env import safety

        if layout_purpose not in PURPOSES:
            raise ValueError(f"layout_purpose must be one of {sorted(PURPOSES)}, got {layout_purpose!r}")
        self.cfg = cfg
        self.K = num_envs
        self.spec = SCENARIOS[cfg.scenario]
        self.seed, self.layout_purpose = seed, layout_purpose
        self.scene = SceneBatch(num_envs, self.spec.nominal)   # every env's current layout
        self.layout_episode = np.zeros(num_envs, np.int64)     # episodes each env has started
        self.phys = TransportPhysics(self.spec, cfg, num_envs)
        self.max_rows = cfg.max_rows
        self.max_steps = cfg.episode_steps
        self.safety_cfg = safety_config(cfg)
        self._safety_model = safety.SafetyModel(self.scene.walls, self.safety_cfg, num_envs)
        K = num_envs
        noise = observation_noise_std(cfg)
        self._obs_noise_std = noise.astype(np.float32) if cfg.randomize and noise.any() else None
        # each env's next NOISE_BLOCK noise draws, drawn in one call of its RNG (the same stream
        # as one call per step); _noise_used counts the draws taken from the block
        self._noise_block = np.empty((K, self.NOISE_BLOCK, N_CARRIERS, OBS_DIM), np.float32)
        self.reseed(seed)
        self.payload_mass = np.full(K, PAYLOAD_MASS)
        d = cfg.action_delay_steps
        self._act_queue = np.zeros((K, d, JOINT_ACT_DIM)) if d else None   # sent, not yet executed
        self.executed_action = np.zeros((K, JOINT_ACT_DIM))                 # last step's executed a
        self.s_prev = np.zeros(K)
        self.s_start = np.zeros(K)
        self.goal_s = self.scene.route_length.copy()
        self._start = np.zeros((K, 3))   # the episode's start pose (payload x, y, yaw)
        self._start_box = np.asarray(self.spec.start_range, np.float64) * cfg.start_spread   # _draw_start's box
        self.goal_xy = np.zeros((K, 2))
        self.goal_yaw = np.zeros(K)
        self.t = np.zeros(K, dtype=np.int64)
        self._acc_all = np.zeros((6, K))   # per-episode sums; _acc names its rows
        self._acc = dict(zip(("ret", "col", "margin", "tilt", "head", "height"), self._acc_all))
        self._min_clear = np.full(K, np.inf)
        self._stillness = task.StillnessClock(cfg, K)   # deadlock vs timeout (EnvConfig.deadlock_*)
        self.fixed_mask = np.zeros((K, JOINT_ACT_DIM), dtype=bool)
        self.human = None
        if cfg.human_slot is not None:
            self.fixed_mask[:, 3 * cfg.human_slot:3 * cfg.human_slot + 3] = True
            self.human = ScriptedHuman(cfg.human_slot, cfg, K)
        self.human_action = np.zeros((K, JOINT_ACT_DIM))
        self.snap = Snapshot.empty(K)   # the current state's snapshot, updated in place
        self._all = np.arange(K)
        self._started = False

    def reseed(self, seed: int) -> None:
        """Restart every env's random streams from ``seed``: the next ``reset`` draws the
        episodes a fresh ``BatchEnv(cfg, K, seed)`` would (the compiled model is kept)."""
        seeds = np.random.SeedSequence(seed).spawn(self.K)
        # env k's start/goal/mass (and scripted human) draws; its observation noise has its own
        # stream (a child of the same seed), so noise settings never move the starts
        self.rngs = [np.random.default_rng(s) for s in seeds]
        self.noise_rngs = [np.random.default_rng(s.spawn(1)[0]) for s in seeds]
        self._noise_used = np.full(self.K, self.NOISE_BLOCK)
        # the layout stream is keyed by (seed, purpose, env, episode): it restarts with the seed
        self.seed = seed
        self.layout_episode[:] = 0

    # --- episode start -------------------------------------------------------------
    START_TRIES = 100   # redraws of a start closer than start_min_clearance to a wall
    NOISE_BLOCK = 32    # observation-noise draws per env and RNG call

    @property
    def walls_array(self) -> np.ndarray:
        """[K,W,5] every env's current walls (a live view: each reset writes its env's row)."""
        return self.scene.walls

    @property
    def routes(self):
        """Every env's current route (``scenarios.Route``)."""
        return self.scene.routes

    def start_clearance(self, xy, yaw: float, env: int = 0) -> float:
        """Formation clearance (payload boundary points, carrier discs; as ``Snapshot.clearance``)
        of a start pose with the carriers on their grasps, in env ``env``'s walls (a kernel;
        ``reference.start_clearance``)."""
        return float(kernels.pose_clearance(float(xy[0]), float(xy[1]), float(yaw), PAYLOAD_POINTS_LOCAL,
                                            GRASP_LOCAL, self.scene.tables[env], CARRIER_RADIUS))

    def _draw_start(self, rng, k: int):
        """Start pose uniform in the scenario box x start_spread around env k's route start, redrawn
        until its clearance is >= start_min_clearance (the route start, 0.25 m clear in every
        nominal scenario, after START_TRIES misses)."""
        route = self.scene.routes[k]
        (x0, y0), yaw0 = route.points[0].tolist(), float(route.heading[0])
        c, s = np.cos(yaw0).item(), np.sin(yaw0).item()   # from_frame(off, yaw0) in scalars, the same arithmetic
        for _ in range(self.START_TRIES):
            ox, oy, oyaw = (rng.uniform(-1.0, 1.0, 3) * self._start_box).tolist()
            xy, yaw = (x0 + (c * ox - s * oy), y0 + (s * ox + c * oy)), yaw0 + oyaw
            if self.start_clearance(xy, yaw, k) >= self.cfg.start_min_clearance:
                return xy, yaw
        return (x0, y0), yaw0

    def draw_layout(self, k: int, episode: int):
        """Env k's layout of its episode ``episode`` (nominal unless randomize and layout_spread > 0)."""
        cfg = self.cfg
        if not cfg.randomize or cfg.layout_spread == 0:
            return self.spec.nominal
        return draw_layout(self.spec, layout_rng(self.seed, self.layout_purpose, k, episode), cfg.layout_spread)

    def _draw_episode(self, k: int):
        """Env k's episode draws: its layout from its layout stream (into ``scene``, the physics and
        the safety model: one geometry for all three), then from its RNG the start pose, goal arc
        length and payload mass, into ``_start[k]``, ``goal_s[k]``, ``payload_mass[k]``."""
        layout = self.draw_layout(k, int(self.layout_episode[k]))
        self.layout_episode[k] += 1
        self.scene.set(k, layout)
        self._safety_model.set_walls(k, layout.walls)
        rng, route, cfg = self.rngs[k], self.scene.routes[k], self.cfg
        xy, yaw = route.points[0], float(route.heading[0])
        goal_s = route.length
        mass = PAYLOAD_MASS
        if cfg.randomize:
            xy, yaw = self._draw_start(rng, k)
            goal_s -= rng.uniform(0.0, self.spec.goal_range)
            mass = float(rng.uniform(*cfg.payload_mass_range))
        self._start[k] = xy[0], xy[1], yaw
        self.goal_s[k] = goal_s
        self.payload_mass[k] = mass
        self.phys.set_episode_model(k, mass, layout.walls)

    def _reset_envs(self, envs):
        """Start new episodes in envs ``envs`` (sorted indices) and snapshot them."""
        for k in envs:
            self._draw_episode(k)
        if self._act_queue is not None:
            self._act_queue[envs] = 0.0
        carriers = self._place_episodes(envs)
        start = self._start[envs]
        self.phys.reset(envs, start[:, :2], start[:, 2], carriers)
        s = np.array([self.scene.routes[k].project(start[j:j + 1, :2], np.zeros(1))[0] for j, k in enumerate(envs)])
        self.s_prev[envs] = s
        self.s_start[envs] = s
        self.t[envs] = 0
        self._acc_all[:, envs] = 0.0
        self._min_clear[envs] = np.inf
        observations.snapshot(self.phys, self.scene, self.s_prev, self.goal_s, self.cfg, self.snap, envs)
        self._stillness.restart(envs, self.snap.pxy[envs], self.snap.pyaw[envs])

    def _place_episodes(self, envs):
        """Goal poses (``goal_xy``, ``goal_yaw`` of envs) of the drawn episodes and their carrier
        poses [n,3,3] on the grasps of the start pose, in one kernel call;
        ``reference.place_episodes`` is the numpy computation."""
        sc = self.scene
        carriers = np.empty((len(envs), N_CARRIERS, 3))
        kernels.place_episodes(envs, self._start, self.goal_s, sc.route_points, sc.route_heading, sc.route_n,
                               sc.route_ds, GRASP_LOCAL, FACING, self.goal_xy, self.goal_yaw, carriers)
        return carriers

    def reset(self) -> dict:
        self._reset_envs(self._all)
        self._started = True
        return self._observe(reset_human=np.ones(self.K, dtype=bool))

    # --- observation, rows, human --------------------------------------------------
    def _progress(self, s):
        """Route progress [K] in [0, 1] of arc lengths s [K] from the episodes' start to goal."""
        return np.minimum(np.maximum((s - self.s_start) / np.maximum(self.goal_s - self.s_start, 1e-6), 0.0), 1.0)

    def _observe(self, reset_human=None) -> dict:
        """The step's output for the current snapshot: observations (noisy), state, rows, human."""
        cfg, snap, K = self.cfg, self.snap, self.K
        progress = self._progress(snap.s)
        obs = np.empty((K, N_CARRIERS, OBS_DIM), np.float32)
        state = np.empty((K, STATE_DIM), np.float32)
        observations.observe(snap, self.scene, self.goal_xy, self.goal_yaw, progress, 1.0 - self.t / self.max_steps,
                             cfg, self._all, obs, state)
        self._add_noise(obs, self._all)   # the trees' view; state and rows stay true
        C, c, row_mask, *_ = self._safety_model.rows(snap.cxy, snap.cyaw, snap.pxy, snap.pyaw, PAYLOAD_POINTS_LOCAL,
                                                     GRASP_LOCAL, PAIR_REST)
        if self.human is not None:
            intended = scripted_actions(snap, cfg)
            if reset_human is not None:
                for k in np.flatnonzero(reset_human):
                    self.human.reset(k, intended)
            h = cfg.human_slot
            self.human_action[:, 3 * h:3 * h + 3] = self.human.act(intended, self.rngs)
        return {
            "obs": obs, "state": state, "C": C, "c": c, "row_mask": row_mask, "fixed_mask": self.fixed_mask.copy(),
            "human_action": self.human_action.copy(), "progress": progress,
        }

    def _add_noise(self, obs, envs):
        """Add envs' next observation noise draws (if any; each env's own stream) to rows ``envs``
        of obs [K,3,OBS_DIM] (a kernel; ``reference.add_noise``)."""
        if self._obs_noise_std is not None:
            self._refill_noise(envs)
            kernels.add_noise(envs, self._noise_block, self._noise_used, self._obs_noise_std, obs)

    def _refill_noise(self, envs):
        """Draw the next NOISE_BLOCK noise draws of envs whose block is used up."""
        used = self._noise_used
        for k in envs[used[envs] == self.NOISE_BLOCK]:
            self.noise_rngs[k].standard_normal(dtype=np.float32, out=self._noise_block[k])
            used[k] = 0

    def scripted_actions(self) -> np.ndarray:
        """Reference controller's actions [K,9] for the current state."""
        return scripted_actions(self.snap, self.cfg)

    def _margin_violation(self, snap) -> np.ndarray:
        """[K] bool: some true barrier of the shield's own specification (the rows' margins:
        carrier disc + margin and payload points + margin vs walls, and the formation band
        under ``safety_rows="grasp"``) is below 0 at the snapshot's state. Reuses the
        snapshot's wall distances; a superset of contact (a disc or board in
        contact has a centre/boundary point within its margin of the wall); safety.spec_barrier_min.
        "Below 0" means below -EnvConfig.margin_violation_tol (metrics.margin_violation)."""
        return margin_violation(self._safety_model.barrier_min(snap.car_dist, snap.pay_dist, snap.cxy, PAIR_REST),
                                self.cfg.margin_violation_tol)

    def _accumulate(self, o, margin_violation):
        """Add this step to the episode sums (``_acc``, ``_min_clear``), in one kernel call;
        ``reference.accumulate`` is the numpy computation."""
        snap = self.snap
        kernels.accumulate_episodes(self._acc_all, self._min_clear, o.reward, o.collision, margin_violation,
                                    snap.tilt, o.heading_error, snap.pz, snap.clearance, CARRY_HEIGHT)

    # --- step ------------------------------------------------------------------------
    def step(self, actions) -> dict:
        if not self._started:
            raise RuntimeError("call reset() before step()")
        cfg = self.cfg
        a = np.asarray(actions, dtype=np.float64)
        if a.shape != (self.K, JOINT_ACT_DIM):
            raise ValueError(f"actions must have shape {(self.K, JOINT_ACT_DIM)}, got {a.shape}")
        if not np.isfinite(a).all():
            raise ValueError("actions contain NaN or Inf")
        a = np.minimum(np.maximum(a, -1.0), 1.0)
        if self._act_queue is not None:   # actuation delay: execute what was sent d steps ago
            sent, a = a, self._act_queue[:, 0].copy()
            self._act_queue[:, :-1] = self._act_queue[:, 1:]
            self._act_queue[:, -1] = sent
        if self.human is not None:
            a = np.where(self.fixed_mask, self.human_action, a)
        self.executed_action[:] = a
        self.phys.step(a)
        snap = self.snap
        observations.snapshot(self.phys, self.scene, self.s_prev, self.goal_s, cfg, snap, self._all)
        self.t += 1
        o = task.step_outcome(snap, self.s_prev, self.t, self.max_steps, self.goal_xy, self.goal_yaw, cfg)
        self.s_prev[:] = snap.s
        drop, success, terminated, truncated = o.drop, o.success, o.terminated, o.truncated
        reward, collision = o.reward, o.collision
        if drop.any():
            self.phys.release(np.flatnonzero(drop))

        margin_violation = self._margin_violation(snap)
        self._stillness.update(snap.pxy, snap.pyaw, self.t)

        self._accumulate(o, margin_violation)

        done = terminated | truncated
        K = self.K
        final_obs = np.zeros((K, N_CARRIERS, OBS_DIM), np.float32)
        final_state = np.zeros((K, STATE_DIM), np.float32)
        episodes = []
        ended = np.flatnonzero(done)
        if len(ended):
            # final observations of the ended envs, then new episodes there
            progress = self._progress(snap.s)
            observations.observe(snap, self.scene, self.goal_xy, self.goal_yaw, progress,
                                 1.0 - self.t / self.max_steps, cfg, ended, final_obs, final_state)
            self._add_noise(final_obs, ended)
            acc = self._acc
            for k in ended:
                n = int(self.t[k])
                episodes.append({
                    "scenario": cfg.scenario, "success": bool(success[k]), "drop": bool(drop[k]),
                    "truncated": bool(truncated[k]),
                    "deadlock": bool(truncated[k]) and self._stillness.deadlocked(k, n),
                    "return": float(acc["ret"][k]), "steps": n, "collision_steps": int(acc["col"][k]),
                    "col_per_1k": 1000.0 * acc["col"][k] / n,
                    "margin_violation_steps": int(acc["margin"][k]),
                    "margin_col_per_1k": 1000.0 * acc["margin"][k] / n,
                    "completion_time": n * cfg.control_dt if success[k] else float("nan"),
                    "tilt": acc["tilt"][k] / n, "heading_error": acc["head"][k] / n,
                    "height_error": acc["height"][k] / n, "min_clearance": float(self._min_clear[k]),
                    "progress_per_step": float(progress[k]) / n, "final_progress": float(progress[k]),
                })
            self._reset_envs(ended)
        out = self._observe(reset_human=done)
        out.update(reward=reward, terminated=terminated, truncated=truncated, collision=collision,
                   margin_violation=margin_violation, drop=drop, success=success, final_obs=final_obs,
                   final_state=final_state, episodes=episodes)
        return out
