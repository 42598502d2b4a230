"""The numpy references of common/env's numba kernels: test oracles, not production code.

Each function here is the same computation as one kernel-backed production function or
method, written in plain numpy (``reference.X`` mirrors the production ``X`` named in its
docstring); tests compare the two on random and recorded states (tests/test_env_kernels.py,
tests/test_env_fast.py) and can run a whole ``BatchEnv`` on the references (monkeypatched
in: the free functions that take the object as their first argument become methods when
set on its class). Nothing in production imports this module.
"""
from __future__ import annotations

import math

import numpy as np

from common.env.batch_env import BatchEnv
from common.env.config import EnvConfig
from common.env.geometry import WallSet, from_frame, to_frame, wrap
from common.env.layout import CARRIER_RADIUS, CARRY_HEIGHT, FACING, GRASP_LOCAL, PAYLOAD_POINTS_LOCAL
from common.env.observations import (_RAY_ANGLES, OBS_DIM, OBS_FEATURE_NAMES, RAY_MAX, STATE_DIM, Snapshot,
                                     slot_targets)
from common.env.physics import TransportPhysics, quat_rotate, quat_to_yaw_tilt
from common.env.safety import (_EPS, N_FORMATION_ROWS, PAIRS, SafetyConfig, SafetyGeometry, _check_walls,
                               _pair_terms, payload_points_world, point_box_distance, predictor_matrices)
from common.env.scenarios import Route
from common.env.scene import SceneBatch
from common.env.task import StepOutcome
from common.spec import JOINT_ACT_DIM, N_CARRIERS


# ----------------------------------- geometry (WallSet queries; kernels.signed_distances, nearest_walls, ray_distances)

def local_frame(walls: WallSet, pts):
    """Points [...,2] in every box's frame [...,W,2]."""
    d = pts[..., None, :] - walls.center  # [...,W,2]
    return np.stack([walls.cos * d[..., 0] + walls.sin * d[..., 1],
                     -walls.sin * d[..., 0] + walls.cos * d[..., 1]], -1)


def signed_distance(walls: WallSet, pts):
    """``WallSet.signed_distance``."""
    q = np.abs(local_frame(walls, pts)) - walls.half
    outside = np.linalg.norm(np.maximum(q, 0.0), axis=-1)
    inside = np.minimum(np.max(q, axis=-1), 0.0)
    return outside + inside


def nearest(walls: WallSet, pts):
    """``WallSet.nearest``."""
    loc = local_frame(walls, pts)
    clamped = np.clip(loc, -walls.half, walls.half)
    d = signed_distance(walls, pts)
    k = np.argmin(d, axis=-1)
    delta_loc = np.take_along_axis(clamped - loc, k[..., None, None], axis=-2)[..., 0, :]
    c, s = walls.cos[k], walls.sin[k]
    vec = np.stack([c * delta_loc[..., 0] - s * delta_loc[..., 1],
                    s * delta_loc[..., 0] + c * delta_loc[..., 1]], -1)
    return np.take_along_axis(d, k[..., None], axis=-1)[..., 0], vec


def ray_distance(walls: WallSet, origin, direction, max_dist: float):
    """``WallSet.ray_distance``."""
    lo = local_frame(walls, origin)
    dl = np.stack([walls.cos * direction[..., None, 0] + walls.sin * direction[..., None, 1],
                   -walls.sin * direction[..., None, 0] + walls.cos * direction[..., None, 1]], -1)
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = 1.0 / np.where(np.abs(dl) < 1e-12, 1e-12, dl)
        t1 = (-walls.half - lo) * inv
        t2 = (walls.half - lo) * inv
    tmin = np.max(np.minimum(t1, t2), axis=-1)
    tmax = np.min(np.maximum(t1, t2), axis=-1)
    hit = (tmax >= np.maximum(tmin, 0.0))
    t = np.where(hit, np.maximum(tmin, 0.0), max_dist)
    return np.minimum(np.min(t, axis=-1), max_dist)


# ------------------------------------------------------------------------- route (Route.project; kernels.route_project)

def route_project(route: Route, xy, s_prev, back: float = 0.6, ahead: float = 1.6):
    """``Route.project``."""
    lo = route.index(np.asarray(s_prev) - back)
    width = int(math.ceil((back + ahead) / route.ds)) + 1
    idx = np.minimum(lo[:, None] + np.arange(width)[None, :], len(route.s) - 1)
    d2 = np.sum((route.points[idx] - xy[:, None, :]) ** 2, axis=-1)
    return route.s[idx[np.arange(len(xy)), np.argmin(d2, axis=1)]]


# -------------------------------------- physics (TransportPhysics; kernels.tracker_targets, grasp_strain, reset_states)

def tracker_targets(carrier_pose, ctrl, actions, cfg: EnvConfig) -> np.ndarray:
    """New tracker targets [K,9] from the measured carrier poses [K,3,3], the current targets
    ``ctrl`` [K,9] and stacked actions [K,9] (carrier-frame, in [-1,1]): what the kernel
    ``TransportPhysics.targets`` runs computes.

    The target integrates the commanded displacements (so a stiff tracker holds the
    commanded formation and inconsistent commands strain the grasps) but is kept
    within ``target_leash`` of the measured pose, so a carrier blocked by a wall
    does not wind up.
    """
    K = len(carrier_pose)
    a = np.clip(np.asarray(actions, dtype=np.float64).reshape(K, N_CARRIERS, 3), -1.0, 1.0)
    pose = carrier_pose
    c, s = np.cos(pose[..., 2]), np.sin(pose[..., 2])
    t = np.array(ctrl, dtype=np.float64).reshape(K, N_CARRIERS, 3)
    lx, ly = cfg.target_leash, cfg.target_leash * cfg.max_step_yaw / cfg.max_step_xy
    t[..., 0] = np.clip(t[..., 0], pose[..., 0] - lx, pose[..., 0] + lx) + (c * a[..., 0] - s * a[..., 1]) * cfg.max_step_xy
    t[..., 1] = np.clip(t[..., 1], pose[..., 1] - lx, pose[..., 1] + lx) + (s * a[..., 0] + c * a[..., 1]) * cfg.max_step_xy
    t[..., 2] = np.clip(t[..., 2], pose[..., 2] - ly, pose[..., 2] + ly) + a[..., 2] * cfg.max_step_yaw
    return t.reshape(K, N_CARRIERS * 3)


def grasp_strain(phys: TransportPhysics):
    """``TransportPhysics.grasp_strain``."""
    grasp3 = np.concatenate([GRASP_LOCAL, np.zeros((N_CARRIERS, 1))], axis=1)[None]   # grasp points, payload frame
    grasp_w = phys.payload_pos[:, None, :] + quat_rotate(phys.payload_quat, np.broadcast_to(grasp3, (phys.K, 3, 3)))
    cp = phys.carrier_pose
    hand = np.concatenate([cp[..., :2], np.full((phys.K, N_CARRIERS, 1), CARRY_HEIGHT)], axis=-1)
    return np.linalg.norm(grasp_w - hand, axis=-1)


def physics_reset(phys: TransportPhysics, envs, payload_xy, payload_yaw, carrier_pose):
    """``TransportPhysics.reset``."""
    envs, xy, yaw, pose = phys._placement(envs, payload_xy, payload_yaw, carrier_pose)
    phys._sync_models()
    phys.batch.state[envs] = phys._reset_state   # as mj_resetData: an env is its state row
    q = phys.qpos[envs]   # the reset state's qpos, then the placement
    a = phys.payload_qadr
    q[:, a:a + 2] = xy
    q[:, a + 2] = CARRY_HEIGHT
    q[:, a + 3:a + 7] = 0.0
    q[:, a + 3] = np.cos(yaw / 2)
    q[:, a + 6] = np.sin(yaw / 2)
    q[:, phys.carrier_qadr.reshape(-1)] = pose
    phys.qpos[envs] = q
    phys._ctrl[envs] = pose
    phys._eq_active[envs] = 1.0
    phys.released[envs] = False
    phys.contact[envs] = False


def physics_targets(phys: TransportPhysics, actions):
    """``TransportPhysics.targets``."""
    phys._ctrl[:] = tracker_targets(phys.carrier_pose, phys._ctrl, actions, phys.cfg)
    return phys._ctrl


# ------------------------------------ BatchEnv (kernels.pose_clearance, place_episodes, add_noise, accumulate_episodes)

def start_clearance(batch: BatchEnv, xy, yaw: float, env: int = 0) -> float:
    """``BatchEnv.start_clearance``."""
    walls = batch.scene.wallsets[env]
    pts = xy + from_frame(PAYLOAD_POINTS_LOCAL, yaw)
    cxy = xy + from_frame(GRASP_LOCAL, yaw)
    return float(min(signed_distance(walls, pts).min(),
                     signed_distance(walls, cxy).min() - CARRIER_RADIUS))


def place_episodes(batch: BatchEnv, envs):
    """``BatchEnv._place_episodes``."""
    start = batch._start[envs]
    xy, yaw = start[:, :2], start[:, 2]
    for k in envs:
        batch.goal_xy[k], batch.goal_yaw[k] = batch.scene.routes[k].pose(batch.goal_s[k])
    carriers = np.empty((len(envs), N_CARRIERS, 3))
    carriers[..., :2] = xy[:, None] + from_frame(GRASP_LOCAL, yaw[:, None])
    carriers[..., 2] = yaw[:, None] + FACING
    return carriers


def add_noise(batch: BatchEnv, obs, envs):
    """``BatchEnv._add_noise``."""
    if batch._obs_noise_std is not None:
        batch._refill_noise(envs)
        used = batch._noise_used
        obs[envs] += batch._noise_block[envs, used[envs]] * batch._obs_noise_std
        used[envs] += 1


def accumulate(batch: BatchEnv, o, margin_violation):
    """``BatchEnv._accumulate``."""
    acc, snap = batch._acc, batch.snap
    acc["ret"] += o.reward
    acc["col"] += o.collision
    acc["margin"] += margin_violation
    acc["tilt"] += np.degrees(snap.tilt)
    acc["head"] += o.heading_error
    acc["height"] += np.abs(snap.pz - CARRY_HEIGHT)
    np.minimum(batch._min_clear, snap.clearance, out=batch._min_clear)


# ------------------------------------------------------------------- observations (kernels.snapshot_rows, observe_rows)

def snapshot(phys: TransportPhysics, scene: SceneBatch, s_prev, goal_s, cfg: EnvConfig, out: Snapshot,
                       envs):
    """``observations.snapshot`` (with the references of the geometry queries), env by env."""
    strain = grasp_strain(phys)
    for k in np.atleast_1d(envs):
        route, walls = scene.routes[k], scene.wallsets[k]
        cp = phys.carrier_pose[[k]]
        pos = phys.payload_pos[[k]]
        yaw, tilt = quat_to_yaw_tilt(phys.payload_quat[[k]])
        pxy = pos[:, :2].copy()
        s = route_project(route, pxy, s_prev[[k]])
        s_look = np.minimum(s + cfg.lookahead, goal_s[[k]])
        look_xy, look_yaw = route.pose(s_look)
        _, route_yaw = route.pose(s)
        pts = pxy[:, None, :] + from_frame(PAYLOAD_POINTS_LOCAL[None], yaw[:, None])
        pay_dist, pay_vec = nearest(walls, pts)
        car_dist = np.min(signed_distance(walls, cp[..., :2]), axis=-1, initial=np.inf)
        d_car = car_dist.min(axis=-1) - CARRIER_RADIUS
        out.put([k], Snapshot(
            cxy=cp[..., :2].copy(), cyaw=cp[..., 2].copy(), cvel=phys.carrier_vel[[k]], pxy=pxy,
            pz=pos[:, 2].copy(), pyaw=yaw, tilt=tilt, pvel=phys.payload_vel[[k]], strain=strain[[k]], s=s,
            look_xy=look_xy, look_yaw=look_yaw, route_yaw=route_yaw, contact=phys.contact[[k]].copy(),
            clearance=np.minimum(pay_dist.min(axis=1), d_car), pay_dist=pay_dist, pay_vec=pay_vec, car_dist=car_dist,
        ))


def observe(snap: Snapshot, scene: SceneBatch, goal_xy, goal_yaw, progress, time_left, cfg: EnvConfig,
                      envs, obs, state):
    """``observations.observe``, env by env (each in its own walls)."""
    for k in np.atleast_1d(envs):
        e = [k]
        sub = snap.take(e)
        o = observations(sub, scene.wallsets[k], goal_xy[e], goal_yaw[e], progress[e], time_left[e], cfg)
        obs[e] = o
        state[e] = global_state(sub, o, goal_xy[e], goal_yaw[e], progress[e], time_left[e],
                                          cfg.human_slot, cfg)


def observations(snap: Snapshot, walls, goal_xy, goal_yaw, progress, time_left, cfg: EnvConfig):
    """Per-carrier observations [K,3,OBS_DIM] float32 (order of OBS_FEATURE_NAMES) of a snapshot of K envs."""
    K = len(snap.pxy)
    cyaw = snap.cyaw
    out = np.empty((K, N_CARRIERS, OBS_DIM), dtype=np.float32)
    col = 0

    def put(x):
        nonlocal col
        x = np.asarray(x)
        if x.ndim == 2:  # [K,3] -> one feature
            out[..., col] = x
            col += 1
        else:            # [K,3,n]
            out[..., col:col + x.shape[-1]] = x
            col += x.shape[-1]

    v_scale = cfg.max_step_xy / cfg.control_dt
    put(to_frame(snap.cvel[..., :2], cyaw) / v_scale)
    put(snap.cvel[..., 2] / (cfg.max_step_yaw / cfg.control_dt))
    slot, slot_yaw = slot_targets(snap)
    put(to_frame(slot - snap.cxy, cyaw) / cfg.lookahead)
    put(wrap(slot_yaw - cyaw))
    grasp_w = snap.pxy[:, None, :] + from_frame(np.broadcast_to(GRASP_LOCAL, (K, 3, 2)), snap.pyaw[:, None])
    put(to_frame(grasp_w - snap.cxy, cyaw) / cfg.drop_strain)
    put(snap.strain / cfg.drop_strain)
    put(to_frame(snap.pxy[:, None, :] - snap.cxy, cyaw))
    rel = snap.pyaw[:, None] - cyaw
    put(np.sin(rel))
    put(np.cos(rel))
    put(np.broadcast_to(wrap(snap.look_yaw - snap.pyaw)[:, None], (K, 3)))
    put(to_frame(np.broadcast_to((snap.look_xy - snap.pxy)[:, None, :], (K, 3, 2)), cyaw) / cfg.lookahead)
    put(np.clip(to_frame(np.broadcast_to((goal_xy - snap.pxy)[:, None, :], (K, 3, 2)), cyaw) / 5.0, -2.0, 2.0))
    put(np.broadcast_to(wrap(goal_yaw - snap.pyaw)[:, None], (K, 3)))
    put(np.broadcast_to(progress[:, None], (K, 3)))
    for off in (1, 2):
        j = (np.arange(3) + off) % 3
        put(to_frame(snap.cxy[:, j] - snap.cxy, cyaw) / 2.0)
        put(snap.strain[:, j] / cfg.drop_strain)
    ray_yaw = cyaw[..., None] + _RAY_ANGLES                                  # [K,3,4]
    dirs = np.stack([np.cos(ray_yaw), np.sin(ray_yaw)], -1)
    origin = np.broadcast_to(snap.cxy[:, :, None, :], dirs.shape)
    ray = ray_distance(walls, origin, dirs, RAY_MAX + CARRIER_RADIUS) - CARRIER_RADIUS
    put(np.clip(ray, -CARRIER_RADIUS, RAY_MAX) / RAY_MAX)
    d, vec = snap.pay_dist, snap.pay_vec                                      # [K,P], [K,P,2]
    p = np.argmin(d, axis=1)
    dmin = d[np.arange(K), p]
    vmin = vec[np.arange(K), p]
    put(np.broadcast_to(np.minimum(dmin, 2.0)[:, None], (K, 3)))
    put(to_frame(np.broadcast_to(vmin[:, None, :], (K, 3, 2)), cyaw))
    put(np.broadcast_to(time_left[:, None], (K, 3)))
    assert col == OBS_DIM
    return out


def global_state(snap: Snapshot, obs, goal_xy, goal_yaw, progress, time_left, human_slot, cfg: EnvConfig):
    """Centralized-critic state [K,STATE_DIM] float32 of a snapshot of K envs: the team's situation
    in the payload frame (``obs``: their noise-free observations)."""
    K = len(snap.pxy)
    v_scale = cfg.max_step_xy / cfg.control_dt
    w_scale = cfg.max_step_yaw / cfg.control_dt
    hs = np.zeros((K, 3))
    if human_slot is not None:
        hs[:, human_slot] = 1.0
    parts = [
        snap.pxy / 10.0, np.cos(snap.pyaw)[:, None], np.sin(snap.pyaw)[:, None],
        to_frame(snap.pvel[:, :2], snap.pyaw) / v_scale, snap.pvel[:, 5:6] / w_scale,
        ((snap.pz - CARRY_HEIGHT) / 0.1)[:, None], snap.tilt[:, None] * 10.0,
        (to_frame(snap.cxy - snap.pxy[:, None, :], snap.pyaw[:, None]) - GRASP_LOCAL).reshape(K, 6) / cfg.drop_strain,
        wrap(snap.cyaw - snap.pyaw[:, None] - FACING),
        (to_frame(snap.cvel[..., :2], snap.pyaw[:, None]) / v_scale).reshape(K, 6),
        snap.cvel[..., 2] / w_scale,
        to_frame(snap.look_xy - snap.pxy, snap.pyaw) / cfg.lookahead,
        wrap(snap.look_yaw - snap.pyaw)[:, None],
        np.clip(to_frame(goal_xy - snap.pxy, snap.pyaw) / 5.0, -2, 2),
        wrap(goal_yaw - snap.pyaw)[:, None],
        progress[:, None],
        snap.strain / cfg.drop_strain,
        np.minimum(snap.clearance, 2.0)[:, None],
        obs[:, :, OBS_FEATURE_NAMES.index("wall_dist_front"):OBS_FEATURE_NAMES.index("wall_dist_right") + 1].reshape(K, 12),
        time_left[:, None],
        hs,
    ]
    out = np.concatenate([np.asarray(p, dtype=np.float64).reshape(K, -1) for p in parts], axis=1)
    assert out.shape[1] == STATE_DIM, out.shape
    return out.astype(np.float32)


# ------------------------------------------------------------------------------------- task (kernels.step_outcome_rows)

def step_outcome(snap, s_old: np.ndarray, t: np.ndarray, max_steps: int, goal_xy: np.ndarray,
                           goal_yaw: np.ndarray, cfg: EnvConfig) -> StepOutcome:
    """``task.step_outcome``."""
    w = cfg.reward
    drop = snap.strain.max(axis=1) > cfg.drop_strain
    pos_err = np.linalg.norm(snap.pxy - goal_xy, axis=1)
    yaw_err = np.abs(wrap(snap.pyaw - goal_yaw))
    success = (pos_err < cfg.goal_pos_tol) & (yaw_err < cfg.goal_yaw_tol) & ~drop
    terminated = drop | success
    truncated = (t >= max_steps) & ~terminated
    collision = snap.contact.copy()
    heading_err = np.abs(wrap(snap.route_yaw - snap.pyaw))
    ds = np.clip(snap.s - s_old, -2 * cfg.max_step_xy, 2 * cfg.max_step_xy)
    reward = (w.progress * ds / cfg.max_step_xy - w.heading * heading_err
              - w.strain * np.mean((snap.strain / cfg.drop_strain) ** 2, axis=1)
              - w.collision * collision - w.drop * drop - w.time + w.success * success)
    return StepOutcome(reward=reward, success=success, drop=drop, terminated=terminated, truncated=truncated,
                       collision=collision, heading_error=heading_err)


# ----------------------------------------------------------------------- safety (kernels.spec_barrier_min, safety_rows)

def spec_barrier_min(carrier_sd, payload_sd, carrier_xy, pair_rest, cfg: SafetyConfig) -> np.ndarray:
    """``safety.spec_barrier_min``."""
    carrier_sd = np.asarray(carrier_sd, dtype=np.float64)
    payload_sd = np.asarray(payload_sd, dtype=np.float64)
    K = carrier_sd.shape[0]
    out = np.full(K, np.inf)
    if carrier_sd.size:
        out = np.minimum(out, carrier_sd.reshape(K, -1).min(1) - cfg.carrier_radius)
    if payload_sd.size:
        out = np.minimum(out, payload_sd.reshape(K, -1).min(1) - cfg.payload_margin)
    if cfg.formation_budget:
        dist, _ = _pair_terms(np.asarray(carrier_xy, dtype=np.float64))
        dev = np.abs(dist - np.asarray(pair_rest, dtype=np.float64))
        out = np.minimum(out, (cfg.grasp_tol - dev).min(1))
    return out


def _wall_rows(points, B, walls, margin, per_entity, budget, cfg):
    """Wall rows of one kind: ``C [K,budget,9], c, mask, h, entity, wall``.

    ``points [K,E,2]`` with predictor matrices ``B [K,E,2,9]``. Per entity the
    ``per_entity`` smallest-h walls within ``search_radius`` are candidates; the
    kind keeps its ``budget`` smallest-h candidates, sorted ascending.
    """
    K, E = points.shape[:2]
    W = walls.shape[1]
    out_C = np.zeros((K, budget, JOINT_ACT_DIM))
    out_c = np.zeros((K, budget))
    out_h = np.zeros((K, budget))
    out_mask = np.zeros((K, budget), dtype=bool)
    out_ent = np.full((K, budget), -1, dtype=np.int64)
    out_wall = np.full((K, budget), -1, dtype=np.int64)
    take = min(per_entity, W)
    if budget == 0 or take == 0 or E == 0:
        return out_C, out_c, out_mask, out_h, out_ent, out_wall
    sd, q, n = point_box_distance(points, walls)
    h = sd - margin                                               # [K,E,W]
    near = np.argsort(h, axis=2, kind="stable")[:, :, :take]      # per-entity nearest walls
    h_near = np.take_along_axis(h, near, 2).reshape(K, E * take)
    key = np.where(h_near <= cfg.search_radius, h_near, np.inf)
    order = np.argsort(key, axis=1, kind="stable")[:, :budget]    # smallest h per kind
    n_kept = order.shape[1]
    ent = order // take
    wall = np.take_along_axis(near.reshape(K, E * take), order, 1)
    kk = np.arange(K)[:, None]
    n_sel = n[kk, ent, wall]                                      # [K,m,2]
    B_sel = B[kk, ent]                                            # [K,m,2,9]
    h_sel = h[kk, ent, wall]
    C = np.einsum("kma,kmab->kmb", n_sel, B_sel)                  # n^T B
    mask = np.isfinite(np.take_along_axis(key, order, 1)) & (np.abs(C).max(-1) > _EPS)
    out_C[:, :n_kept] = np.where(mask[..., None], C, 0.0)
    out_c[:, :n_kept] = np.where(mask, -cfg.alpha * h_sel, 0.0)   # n·(p⁺-q) - r >= (1-α)h
    out_h[:, :n_kept] = np.where(mask, h_sel, 0.0)
    out_mask[:, :n_kept] = mask
    out_ent[:, :n_kept] = np.where(mask, ent, -1)
    out_wall[:, :n_kept] = np.where(mask, wall, -1)
    return out_C, out_c, out_mask, out_h, out_ent, out_wall


def _formation_rows(geom, carrier_B, cfg):
    """Two rows per pair keeping |D - D0| <= grasp_tol, linearized along the pair unit vector."""
    dist, unit = _pair_terms(geom.carrier_xy)                     # [K,3], [K,3,2]
    i, k = np.array(PAIRS).T
    rel_B = carrier_B[:, i] - carrier_B[:, k]                     # [K,3,2,9]
    dD = np.einsum("kpa,kpab->kpb", unit, rel_B)                  # D⁺ ≈ D + dD a
    h_lo = dist - (geom.pair_rest - cfg.grasp_tol)
    h_hi = (geom.pair_rest + cfg.grasp_tol) - dist
    C = np.stack([dD, -dD], 2).reshape(-1, N_FORMATION_ROWS, JOINT_ACT_DIM)
    h = np.stack([h_lo, h_hi], 2).reshape(-1, N_FORMATION_ROWS)
    mask = np.repeat(dist > _EPS, 2, axis=1) & (np.abs(C).max(-1) > _EPS)
    C = np.where(mask[..., None], C, 0.0)
    c = np.where(mask, -cfg.alpha * h, 0.0)                       # h + C a >= (1-α) h
    ent = np.repeat(np.arange(len(PAIRS)), 2)[None].repeat(len(C), 0)
    return C, c, mask, h, ent


def build_rows(geom: SafetyGeometry, walls: np.ndarray, cfg: SafetyConfig):
    """``safety.build_rows``: affine rows ``C a >= c`` (Eq. joint_safety_rows) for the next
    stacked action; the same arrays."""
    if not isinstance(geom, SafetyGeometry):
        raise TypeError(f"geom must be a SafetyGeometry, got {type(geom).__name__}")
    K = geom.num_envs
    walls = _check_walls(walls, K)
    carrier_B, point_B, _ = predictor_matrices(geom, cfg)
    carrier = _wall_rows(geom.carrier_xy, carrier_B, walls, cfg.carrier_radius,
                         int(cfg.walls_per_carrier), cfg.carrier_budget, cfg)
    payload = _wall_rows(payload_points_world(geom), point_B, walls, cfg.payload_margin,
                         int(cfg.walls_per_point), cfg.payload_budget, cfg)
    fb = cfg.formation_budget
    if fb:
        form = _formation_rows(geom, carrier_B, cfg)
    else:  # "paper": no formation slots
        form = (np.zeros((K, 0, JOINT_ACT_DIM)), np.zeros((K, 0)), np.zeros((K, 0), dtype=bool),
                np.zeros((K, 0)), np.zeros((K, 0), dtype=np.int64))
    C = np.concatenate([carrier[0], payload[0], form[0]], 1)
    c = np.concatenate([carrier[1], payload[1], form[1]], 1)
    mask = np.concatenate([carrier[2], payload[2], form[2]], 1)
    kinds = cfg.slot_kinds
    info = {
        "h": np.concatenate([carrier[3], payload[3], form[3]], 1),
        "kind": np.broadcast_to(kinds, (K, len(kinds))).copy(),
        "entity": np.concatenate([carrier[4], payload[4], form[4]], 1),
        "wall": np.concatenate([carrier[5], payload[5], np.full((K, fb), -1)], 1),
    }
    return C, c, mask, info
