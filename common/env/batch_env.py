"""K transport environments in one process (one MjModel, K MjData): the actors' env API.

The batch bookkeeping lives here: start/goal randomization, the graded-outcome
variation (wider starts, payload mass, observation noise, actuation delay; see
EnvConfig), the scripted human slot, auto-reset, safety rows for the next action
and per-episode metrics.
Physics is ``physics.py``; what a step means for the task (reward, success,
drop, termination vs truncation) is ``task.py``. See docs/interfaces.md
(common/env) for the dict returned by ``reset``/``step``.
"""
from __future__ import annotations

import numpy as np

from common.env.config import EnvConfig
from common.env.geometry import WallSet, from_frame
from common.env.layout import (CARRIER_RADIUS, CARRY_HEIGHT, FACING, GRASP_LOCAL, PAIR_REST, PAYLOAD_MASS,
                               PAYLOAD_POINTS_LOCAL)
from common.env.observations import (OBS_DIM, STATE_DIM, global_state, observation_noise_std, observations,
                                     snapshot)
from common.env.physics import TransportPhysics
from common.env.scenarios import SCENARIOS, Route
from common.env.scripted import ScriptedHuman, scripted_actions
from common.env.task import step_outcome
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

    def __init__(self, cfg: EnvConfig, num_envs: int = 1, seed: int = 0):
        from common.env import safety

        self.cfg = cfg
        self.K = num_envs
        self.spec = SCENARIOS[cfg.scenario]
        self.route = Route(self.spec.route)
        self.walls_array = self.spec.walls_array()
        self.walls = WallSet(self.walls_array)
        self.phys = TransportPhysics(self.spec, cfg, num_envs)
        self.max_rows = cfg.max_rows
        self.max_steps = cfg.episode_steps
        self._safety = safety
        self.safety_cfg = safety_config(cfg)
        seeds = np.random.SeedSequence(seed).spawn(num_envs)
        # env k's start/goal/mass (and scripted human) draws; its observation noise has its own
        # stream (a child of the same seed), so noise settings never move the starts
        self.rngs = [np.random.default_rng(s) for s in seeds]
        self.noise_rngs = [np.random.default_rng(s.spawn(1)[0]) for s in seeds]
        K = num_envs
        noise = observation_noise_std(cfg)
        self._obs_noise_std = noise.astype(np.float32) if cfg.randomize and noise.any() else None
        self.payload_mass = np.full(K, PAYLOAD_MASS)
        d = cfg.action_delay_steps
        self._act_queue = np.zeros((K, d, JOINT_ACT_DIM)) if d else None   # sent, not yet executed
        self.executed_action = np.zeros((K, JOINT_ACT_DIM))                 # last step's executed a
        self.s_prev = np.zeros(K)
        self.s_start = np.zeros(K)
        self.goal_s = np.full(K, self.route.length)
        self.goal_xy = np.zeros((K, 2))
        self.goal_yaw = np.zeros(K)
        self.t = np.zeros(K, dtype=np.int64)
        self._acc = {k: np.zeros(K) for k in ("ret", "col", "margin", "tilt", "head", "height")}
        self._min_clear = np.full(K, np.inf)
        self.fixed_mask = np.zeros((K, JOINT_ACT_DIM), dtype=bool)
        self.human = None
        if cfg.human_slot is not None:
            self.fixed_mask[:, 3 * cfg.human_slot:3 * cfg.human_slot + 3] = True
            self.human = ScriptedHuman(cfg.human_slot, cfg, K)
        self.human_action = np.zeros((K, JOINT_ACT_DIM))
        self.snap = None
        self._started = False

    # --- episode start -------------------------------------------------------------
    START_TRIES = 100   # redraws of a start closer than start_min_clearance to a wall

    def start_clearance(self, xy, yaw: float) -> float:
        """Formation clearance (payload boundary points, carrier discs; as ``Snapshot.clearance``)
        of a start pose with the carriers on their grasps."""
        pts = xy + from_frame(PAYLOAD_POINTS_LOCAL, yaw)
        cxy = xy + from_frame(GRASP_LOCAL, yaw)
        return float(min(self.walls.signed_distance(pts).min(),
                         self.walls.signed_distance(cxy).min() - CARRIER_RADIUS))

    def _draw_start(self, rng):
        """Start pose uniform in the scenario box x start_spread, redrawn until its clearance
        is >= start_min_clearance (the nominal start, 0.25 m clear in every scenario, after
        START_TRIES misses)."""
        cfg, route = self.cfg, self.route
        xy0, yaw0 = route.points[0].copy(), float(route.heading[0])
        box = np.asarray(self.spec.start_range, np.float64) * cfg.start_spread
        for _ in range(self.START_TRIES):
            off = rng.uniform(-1.0, 1.0, 3) * box
            xy, yaw = xy0 + from_frame(off[:2], yaw0), yaw0 + off[2]
            if self.start_clearance(xy, yaw) >= cfg.start_min_clearance:
                return xy, yaw
        return xy0, yaw0

    def _reset_env(self, k: int):
        rng, spec, route, cfg = self.rngs[k], self.spec, self.route, self.cfg
        xy, yaw = route.points[0].copy(), float(route.heading[0])
        goal_s = route.length
        mass = PAYLOAD_MASS
        if cfg.randomize:
            xy, yaw = self._draw_start(rng)
            goal_s -= rng.uniform(0.0, spec.goal_range)
            mass = float(rng.uniform(*cfg.payload_mass_range))
        self.payload_mass[k] = mass
        self.phys.set_payload_mass(k, mass)
        if self._act_queue is not None:
            self._act_queue[k] = 0.0
        gxy, gyaw = route.pose(goal_s)
        self.goal_s[k], self.goal_xy[k], self.goal_yaw[k] = goal_s, gxy, gyaw
        carriers = np.zeros((N_CARRIERS, 3))
        carriers[:, :2] = xy + from_frame(GRASP_LOCAL, yaw)
        carriers[:, 2] = yaw + FACING
        self.phys.reset(k, xy, yaw, carriers)
        self.s_prev[k] = route.project(xy[None], np.zeros(1))[0]
        self.s_start[k] = self.s_prev[k]
        self.t[k] = 0
        for a in self._acc.values():
            a[k] = 0.0
        self._min_clear[k] = np.inf

    def reset(self) -> dict:
        for k in range(self.K):
            self._reset_env(k)
        self._started = True
        out = self._observe(reset_human=np.ones(self.K, dtype=bool))
        return out

    # --- observation, rows, human --------------------------------------------------
    def _progress(self, s, idx=slice(None)):
        return np.clip((s - self.s_start[idx]) / np.maximum(self.goal_s[idx] - self.s_start[idx], 1e-6), 0.0, 1.0)

    def _observe(self, reset_human=None, snap=None) -> dict:
        cfg = self.cfg
        if snap is None:
            snap = snapshot(self.phys, self.route, self.walls, self.s_prev, self.goal_s, cfg)
        self.snap = snap
        progress = self._progress(snap.s)
        time_left = 1.0 - self.t / self.max_steps
        obs = observations(snap, self.walls, self.goal_xy, self.goal_yaw, progress, time_left, cfg)
        state = global_state(snap, obs, self.goal_xy, self.goal_yaw, progress, time_left, cfg.human_slot, cfg)
        obs = self._noisy(obs, range(self.K))   # the trees' view; state and rows stay true
        geom = self._safety.SafetyGeometry(
            carrier_xy=snap.cxy, carrier_yaw=snap.cyaw, payload_xy=snap.pxy, payload_yaw=snap.pyaw,
            payload_points_local=PAYLOAD_POINTS_LOCAL, grasp_local=GRASP_LOCAL, pair_rest=PAIR_REST)
        C, c, row_mask, _ = self._safety.build_rows(geom, self.walls_array, self.safety_cfg)
        self.human_action[:] = 0.0
        if self.human is not None:
            intended = scripted_actions(snap, cfg)
            if reset_human is not None:
                for k in np.flatnonzero(reset_human):
                    self.human.reset(k, intended)
            h = cfg.human_slot
            self.human_action[:, 3 * h:3 * h + 3] = self.human.act(intended, self.rngs)
        return {
            "obs": obs, "state": state, "C": np.asarray(C, np.float64), "c": np.asarray(c, np.float64),
            "row_mask": np.asarray(row_mask, bool), "fixed_mask": self.fixed_mask.copy(),
            "human_action": self.human_action.copy(), "progress": progress,
        }

    def _noisy(self, obs, envs):
        """Observations [n,3,OBS_DIM] of envs ``envs`` plus their observation noise (if any)."""
        if self._obs_noise_std is None:
            return obs
        noise = np.stack([self.noise_rngs[k].standard_normal((N_CARRIERS, OBS_DIM), np.float32) for k in envs])
        return obs + noise * self._obs_noise_std

    def scripted_actions(self) -> np.ndarray:
        """Reference controller's actions [K,9] for the current state."""
        return scripted_actions(self.snap, self.cfg)

    def _margin_violation(self, snap) -> np.ndarray:
        """[K] bool: some true barrier of the shield's own specification (the rows' margins:
        carrier disc + margin and payload points + margin vs walls, and the formation band
        under ``safety_rows="grasp"``) is below 0 at the snapshot's state. Reuses the
        snapshot's wall distances; a superset of contact (a disc or board in
        contact has a centre/boundary point within its margin of the wall)."""
        h_min = self._safety.spec_barrier_min(snap.car_dist, snap.pay_dist, snap.cxy, PAIR_REST, self.safety_cfg)
        return h_min < 0.0

    # --- step ------------------------------------------------------------------------
    def step(self, actions) -> dict:
        if not self._started:
            raise RuntimeError("call reset() before step()")
        cfg = self.cfg
        a = np.asarray(actions, dtype=np.float64)
        if a.shape != (self.K, JOINT_ACT_DIM):
            raise ValueError(f"actions must have shape {(self.K, JOINT_ACT_DIM)}, got {a.shape}")
        if not np.all(np.isfinite(a)):
            raise ValueError("actions contain NaN or Inf")
        a = np.clip(a, -1.0, 1.0)
        if self._act_queue is not None:   # actuation delay: execute what was sent d steps ago
            sent, a = a, self._act_queue[:, 0].copy()
            self._act_queue[:, :-1] = self._act_queue[:, 1:]
            self._act_queue[:, -1] = sent
        if self.human is not None:
            a = np.where(self.fixed_mask, self.human_action, a)
        self.executed_action[:] = a
        s_old = self.s_prev.copy()
        self.phys.step(a)
        snap = snapshot(self.phys, self.route, self.walls, self.s_prev, self.goal_s, cfg)
        self.s_prev = snap.s.copy()
        self.t += 1

        o = step_outcome(snap, s_old, self.t, self.max_steps, self.goal_xy, self.goal_yaw, cfg)
        drop, success, terminated, truncated = o.drop, o.success, o.terminated, o.truncated
        reward, collision, heading_err = o.reward, o.collision, o.heading_error
        for k in np.flatnonzero(drop):
            self.phys.release(k)

        margin_violation = self._margin_violation(snap)

        acc = self._acc
        acc["ret"] += reward
        acc["col"] += collision
        acc["margin"] += margin_violation
        acc["tilt"] += np.degrees(snap.tilt)
        acc["head"] += heading_err
        acc["height"] += np.abs(snap.pz - CARRY_HEIGHT)
        self._min_clear = np.minimum(self._min_clear, snap.clearance)

        done = terminated | truncated
        K = self.K
        final_obs = np.zeros((K, N_CARRIERS, OBS_DIM), np.float32)
        final_state = np.zeros((K, STATE_DIM), np.float32)
        episodes = []
        ended = np.flatnonzero(done)
        if len(ended):
            # final observations of the ended envs only, then reset them and patch the snapshot
            sub = snap.take(ended)
            progress = self._progress(sub.s, ended)
            time_left = 1.0 - self.t[ended] / self.max_steps
            obs_end = observations(sub, self.walls, self.goal_xy[ended], self.goal_yaw[ended], progress, time_left, cfg)
            final_obs[ended] = self._noisy(obs_end, ended)
            final_state[ended] = global_state(sub, obs_end, self.goal_xy[ended], self.goal_yaw[ended], progress,
                                              time_left, cfg.human_slot, cfg)
            for j, k in enumerate(ended):
                n = int(self.t[k])
                episodes.append({
                    "scenario": cfg.scenario, "success": bool(success[k]), "drop": bool(drop[k]),
                    "return": float(acc["ret"][k]), "steps": n, "collision_steps": int(acc["col"][k]),
                    "col_per_1k": 1000.0 * acc["col"][k] / n,
                    "margin_violation_steps": int(acc["margin"][k]),
                    "margin_col_per_1k": 1000.0 * acc["margin"][k] / n,
                    "completion_time": n * cfg.control_dt if success[k] else float("nan"),
                    "tilt": acc["tilt"][k] / n, "heading_error": acc["head"][k] / n,
                    "height_error": acc["height"][k] / n, "min_clearance": float(self._min_clear[k]),
                    "progress_per_step": float(progress[j]) / n, "final_progress": float(progress[j]),
                })
                self._reset_env(k)
            snap.put(ended, snapshot(self.phys, self.route, self.walls, self.s_prev[ended], self.goal_s[ended],
                                     cfg, idx=ended))
        out = self._observe(reset_human=done, snap=snap)
        out.update(reward=reward, terminated=terminated, truncated=truncated, collision=collision.copy(),
                   margin_violation=margin_violation, drop=drop, success=success, final_obs=final_obs,
                   final_state=final_state, episodes=episodes)
        return out
