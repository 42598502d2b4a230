"""Predictor honesty: how often actions that satisfy the safety rows keep the true barriers safe.

The CBF statement of Sec. III-B is predictor-level: each row of
Eq. (joint_safety_rows) is a conservative bound on the one-step condition
``h(x⁺) >= (1 - α) h(x)`` *for the linear predictor* of common/env/safety.py.
This module measures the gap to the real MuJoCo step. It rolls K environments
with random actions, projects every action onto the rows with the exact joint
CBF-QP (Eq. qpshield, ``common.shield.qp.solve_cbf_qp``), steps, and evaluates the
*true* barriers (exact distances) at the true next state.

Random actions: each env drives its formation along a random world direction
(resampled every ``drift_steps`` steps, so the formation actually reaches the
walls and the rows bind) plus independent uniform noise per carrier. The drift
gain and noise scale are arguments of :func:`measure_honesty`.

Reported (per scenario):
  * ``rate``: among *eligible* transitions (all true barriers ``>= 0`` now and
    the QP feasible, so the executed action satisfies every row), the fraction
    whose true next state has every barrier ``>= 0``;
  * ``row_rate``: per row kind, the fraction of enforced rows whose own true
    barrier satisfies ``h(x⁺) >= (1 - α) h(x) - tol`` at the true next state;
  * ``unsafe_by``: per barrier family, eligible transitions where it went negative;
  * counts (transitions, eligible, with an active row at the executed action,
    infeasible QPs), the smallest next-state barrier and whether the env's rows
    equal the rows rebuilt from the measured geometry (a wiring check).

``world="predictor"`` replaces MuJoCo by the predictor itself (carriers move
exactly as predicted, payload points as the affine rigid fit, the payload pose
follows the fitted translation and rotation). There the wall rows and the
lower formation rows hold by construction (row_rate 1.0); the upper
formation row is first-order (see common/env/safety.py), which is the only
source of predictor-world misses.
"""
from __future__ import annotations

import numpy as np

from common.env import safety
from common.env.batch_env import BatchEnv, safety_config
from common.env.config import EnvConfig
from common.env.layout import FACING, GRASP_LOCAL, PAIR_REST, PAYLOAD_POINTS_LOCAL
from common.env.physics import quat_to_yaw_tilt
from common.env.scenarios import SCENARIOS, Route
from common.shield.qp import STATUS_OPTIMAL, solve_cbf_qp

KIND_NAMES = {safety.KIND_CARRIER_WALL: "carrier_wall", safety.KIND_PAYLOAD_WALL: "payload_wall",
              safety.KIND_FORMATION: "formation_lo", safety.KIND_FORMATION + 1: "formation_hi"}


# ----------------------------------------------------------------------------- row bookkeeping

def row_barriers(barriers: dict, info: dict, M: int) -> np.ndarray:
    """The barrier each row protects, looked up in a :func:`safety.barrier_values` dict -> [K,M].

    Padding rows get 0. Formation rows ("grasp" profile only) fill the last 6 slots as (lower, upper) per pair.
    """
    K = info["kind"].shape[0]
    kk = np.arange(K)[:, None].repeat(M, 1)
    ent = np.maximum(info["entity"], 0)
    wall = np.maximum(info["wall"], 0)
    out = np.zeros((K, M))
    kind = info["kind"]
    for k_id, key in ((safety.KIND_CARRIER_WALL, "carrier_wall"), (safety.KIND_PAYLOAD_WALL, "payload_wall")):
        sel = kind == k_id
        if barriers[key].shape[-1] and sel.any():
            out[sel] = barriers[key][kk[sel], ent[sel], wall[sel]]
    sel = kind == safety.KIND_FORMATION
    side = (np.arange(M) - (M - safety.N_FORMATION_ROWS)) % 2     # 0 lower, 1 upper
    side = np.broadcast_to(side, (K, M))
    out[sel] = barriers["formation"][kk[sel], ent[sel], side[sel]]
    return out


def _row_kind_ids(info: dict, M: int) -> np.ndarray:
    """Row kinds with the formation split into lower (2) and upper (3)."""
    ids = info["kind"].copy()
    upper = ((np.arange(M) - (M - safety.N_FORMATION_ROWS)) % 2 == 1) & (ids[0] == safety.KIND_FORMATION)
    ids[:, upper] = safety.KIND_FORMATION + 1
    return ids


def _random_actions(rng, carrier_yaw, drift_dir, gain, noise):
    """Per-carrier actions [K,9]: a world drift in each carrier's frame plus uniform noise."""
    K = carrier_yaw.shape[0]
    c, s = np.cos(carrier_yaw), np.sin(carrier_yaw)
    # R(ψ_i)^T v: the carrier-frame command that moves carrier i along the world direction v
    local = np.stack([c * drift_dir[:, None, 0] + s * drift_dir[:, None, 1],
                      -s * drift_dir[:, None, 0] + c * drift_dir[:, None, 1]], -1)
    a = np.concatenate([gain * local, np.zeros((K, 3, 1))], -1).reshape(K, 9)
    return np.clip(a + rng.uniform(-noise, noise, (K, 9)), -1.0, 1.0)


# ----------------------------------------------------------------------------- worlds

class _MujocoWorld:
    """The real BatchEnv; the true next geometry is read from the physics right after it steps."""

    def __init__(self, scenario: str, num_envs: int, seed: int, safety_rows: str = EnvConfig.safety_rows):
        self.env = BatchEnv(EnvConfig(scenario=scenario, safety_rows=safety_rows), num_envs=num_envs, seed=seed)
        self.walls = self.env.walls_array
        self.cfg = self.env.safety_cfg
        self._next = None
        phys = self.env.phys
        physics_step = phys.step

        def step_and_record(actions):  # capture the state before any auto-reset
            physics_step(actions)
            self._next = self._read()

        phys.step = step_and_record
        self.out = self.env.reset()

    def _read(self) -> safety.SafetyGeometry:
        phys = self.env.phys
        cp = phys.carrier_pose
        yaw, _ = quat_to_yaw_tilt(phys.payload_quat)
        return safety.SafetyGeometry(cp[..., :2].copy(), cp[..., 2].copy(), phys.payload_pos[:, :2].copy(),
                                     yaw, PAYLOAD_POINTS_LOCAL, GRASP_LOCAL, PAIR_REST)

    def geometry(self):
        return self._read()

    def env_rows(self):
        return self.out["C"], self.out["c"], self.out["row_mask"]

    def step(self, a):
        """-> (true barriers at the next state, transition ended in a reset [K])."""
        self.out = self.env.step(a)
        done = self.out["terminated"] | self.out["truncated"]
        return safety.barrier_values(self._next, self.walls, self.cfg), done


class _PredictorWorld:
    """The one-step predictor as the world (the rows' own model)."""

    def __init__(self, scenario: str, num_envs: int, seed: int, safety_rows: str = EnvConfig.safety_rows):
        spec = SCENARIOS[scenario]
        route = Route(spec.route)
        self.walls = spec.walls_array()
        self.cfg = safety_config(EnvConfig(scenario=scenario, safety_rows=safety_rows))  # the env's safety parameters
        rng = np.random.default_rng(seed)
        K = num_envs
        yaw = route.heading[0] + rng.uniform(-1, 1, K) * spec.start_range[2]
        off = rng.uniform(-1, 1, (K, 2)) * spec.start_range[:2]
        pxy = route.points[0] + off
        self.geom = safety.SafetyGeometry(
            np.zeros((K, 3, 2)), yaw[:, None] + FACING, pxy, yaw, PAYLOAD_POINTS_LOCAL, GRASP_LOCAL, PAIR_REST)
        self.geom.carrier_xy = safety.grasp_world(self.geom)

    def geometry(self):
        g = self.geom
        return safety.SafetyGeometry(g.carrier_xy, g.carrier_yaw, g.payload_xy, g.payload_yaw,
                                     g.payload_points_local, g.grasp_local, g.pair_rest)

    def env_rows(self):
        return safety.build_rows(self.geom, self.walls, self.cfg)[:3]

    def step(self, a):
        g, cfg = self.geom, self.cfg
        pred = safety.predict(g, a, cfg)
        barriers = safety.barriers_at_points(pred["carrier_xy"], pred["payload_points"], g.pair_rest,
                                             self.walls, cfg)
        centroid = safety.grasp_world(g).mean(1)
        dtheta = pred["payload_theta"]
        lever = g.payload_xy - centroid
        g.payload_xy = g.payload_xy + pred["payload_translation"] + dtheta[:, None] * np.stack(
            [-lever[:, 1], lever[:, 0]], -1)
        g.payload_yaw = g.payload_yaw + dtheta
        g.carrier_xy, g.carrier_yaw = pred["carrier_xy"], pred["carrier_yaw"]
        return barriers, np.zeros(len(a), dtype=bool)


# ----------------------------------------------------------------------------- measurement

def measure_honesty(scenario: str, n_steps: int, seed: int, num_envs: int = 8, world: str = "mujoco",
                    drift_gain: float = 0.8, noise: float = 0.5, drift_steps: int = 20,
                    tol: float = 1e-9, backend: str = "default", safety_rows: str = EnvConfig.safety_rows) -> dict:
    """Roll ``num_envs`` envs for ``n_steps`` shielded random steps; see the module docstring.
    ``safety_rows`` is the row profile (``EnvConfig.safety_rows``); the formation kinds are
    counted (and their ``row_rate`` defined) only under ``"grasp"``, NaN otherwise."""
    if world not in ("mujoco", "predictor"):
        raise ValueError(f"world must be 'mujoco' or 'predictor', got {world!r}")
    if n_steps < 1 or num_envs < 1:
        raise ValueError("n_steps and num_envs must be positive")
    w = (_MujocoWorld if world == "mujoco" else _PredictorWorld)(scenario, num_envs, seed, safety_rows)
    cfg, K, M = w.cfg, num_envs, w.cfg.max_rows
    rng = np.random.default_rng(seed + 1)
    drift = np.zeros((K, 2))
    counts = dict(transitions=0, eligible=0, safe_next=0, active=0, infeasible=0, rows_match=0)
    row_ok = {name: 0 for name in KIND_NAMES.values()}
    row_n = {name: 0 for name in KIND_NAMES.values()}
    unsafe_by = {"carrier_wall": 0, "payload_wall": 0, "formation": 0}
    min_next_h = np.inf
    for t in range(n_steps):
        if t % drift_steps == 0:
            ang = rng.uniform(-np.pi, np.pi, K)
            drift = np.stack([np.cos(ang), np.sin(ang)], -1)
        geom = w.geometry()
        C, c, mask, info = safety.build_rows(geom, w.walls, cfg)
        C_env, c_env, mask_env = w.env_rows()
        counts["rows_match"] += int(np.sum(np.all(mask == mask_env, 1)
                                           & np.all(np.isclose(C, C_env, atol=1e-9), (1, 2))
                                           & np.all(np.isclose(c, c_env, atol=1e-9), 1)))
        h_now = safety.barrier_values(geom, w.walls, cfg)["min"]
        a_rand = _random_actions(rng, geom.carrier_yaw, drift, drift_gain, noise)
        qp = solve_cbf_qp(a_rand, C, c, mask, backend=backend)
        # transitions that end an episode are still physical steps (the next state is
        # read before the auto-reset): keep them
        nxt, _ = w.step(qp.a_exec)
        feasible = qp.status == STATUS_OPTIMAL
        eligible = feasible & (h_now >= 0.0)
        counts["transitions"] += K
        counts["infeasible"] += int(np.sum(~feasible))
        counts["eligible"] += int(eligible.sum())
        counts["safe_next"] += int(np.sum(eligible & (nxt["min"] >= 0.0)))
        counts["active"] += int(np.sum(eligible & np.any(qp.active & mask, 1)))
        for key in unsafe_by:  # which barrier family went negative on an eligible transition
            neg = nxt[key].reshape(K, -1).min(1, initial=np.inf) < 0.0
            unsafe_by[key] += int(np.sum(eligible & neg))
        if eligible.any():
            min_next_h = min(min_next_h, float(nxt["min"][eligible].min()))
        # row-level discrete CBF condition at the true next state
        h_next = row_barriers(nxt, info, M)
        ok = h_next >= (1.0 - cfg.alpha) * info["h"] - tol
        kinds = _row_kind_ids(info, M)
        enforced = mask & feasible[:, None]
        for k_id, name in KIND_NAMES.items():
            sel = enforced & (kinds == k_id)
            row_n[name] += int(sel.sum())
            row_ok[name] += int(np.sum(ok & sel))
    rate = counts["safe_next"] / counts["eligible"] if counts["eligible"] else float("nan")
    return {
        "scenario": scenario, "world": world, "rate": rate,
        "row_rate": {n: (row_ok[n] / row_n[n] if row_n[n] else float("nan")) for n in row_n},
        "row_count": row_n, "unsafe_by": unsafe_by, "min_next_h": min_next_h, **counts,
    }
