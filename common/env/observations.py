"""Task-side view of the physics: route tracking snapshot, per-carrier observations, global state.

All quantities are vectorized over K environments. Per-carrier features are in the
carrier's own frame (x forward, y left) and scaled to O(1); names are stable
(``OBS_FEATURE_NAMES``) because the audit tools print tree predicates with them.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from common.env import kernels
from common.env.config import EnvConfig
from common.env.geometry import from_frame
from common.env.layout import CARRIER_RADIUS, CARRY_HEIGHT, FACING, GRASP_LOCAL, PAYLOAD_POINTS_LOCAL
from common.env.physics import TransportPhysics
from common.env.scene import PROJECT_BACK, SceneBatch
from common.spec import N_CARRIERS

OBS_FEATURE_NAMES: list[str] = [
    "vel_x", "vel_y", "vel_yaw",                    # own velocity / (max step per control_dt)
    "slot_dx", "slot_dy",                           # carrier -> own grasp slot at the payload's lookahead pose, / lookahead
    "slot_dyaw",                                    # slot yaw (lookahead heading + facing) - own yaw (rad)
    "grasp_dx", "grasp_dy", "grasp_strain",         # carrier -> own grasp point on the payload now, / drop_strain
    "payload_dx", "payload_dy",                     # carrier -> payload centre (m)
    "payload_sin", "payload_cos",                   # payload yaw relative to own yaw
    "heading_err",                                  # route heading at lookahead - payload yaw (rad)
    "lookahead_dx", "lookahead_dy",                 # payload centre -> route lookahead point, / lookahead
    "goal_dx", "goal_dy", "goal_dyaw",              # payload -> goal (/5 m, clipped to +-2) and goal yaw error (rad)
    "progress",                                     # route progress in [0, 1]
    "partner1_dx", "partner1_dy", "partner1_strain",  # carrier (i+1)%3 relative position (/2 m) and strain
    "partner2_dx", "partner2_dy", "partner2_strain",  # carrier (i+2)%3
    "wall_dist_front", "wall_dist_left", "wall_dist_back", "wall_dist_right",  # free ray length beyond the carrier disc / 2 m
    "payload_clearance",                            # min distance of payload boundary points to walls (m, capped at 2)
    "payload_wall_dx", "payload_wall_dy",           # nearest payload point -> nearest wall point (m)
    "time_left",                                    # 1 - t / max_steps
]
OBS_DIM = len(OBS_FEATURE_NAMES)
RAY_MAX = 2.0
_RAY_ANGLES = np.array([0.0, np.pi / 2, np.pi, -np.pi / 2])


def feature_units(cfg: EnvConfig) -> dict[str, tuple[float, str]]:
    """Per feature: ``(scale, unit)`` with feature = physical quantity / scale,
    the quantity in the carrier's own frame (x forward, y left) -- what the
    audit tools print tree predicates in (``goal_dx > 1.55 m``)."""
    v, w = cfg.max_step_xy / cfg.control_dt, cfg.max_step_yaw / cfg.control_dt
    la, ds = cfg.lookahead, cfg.drop_strain
    out = {"vel_x": (v, "m/s"), "vel_y": (v, "m/s"), "vel_yaw": (w, "rad/s"),
           "slot_dx": (la, "m"), "slot_dy": (la, "m"), "slot_dyaw": (1.0, "rad"),
           "grasp_dx": (ds, "m"), "grasp_dy": (ds, "m"), "grasp_strain": (ds, "m"),
           "payload_dx": (1.0, "m"), "payload_dy": (1.0, "m"), "payload_sin": (1.0, ""), "payload_cos": (1.0, ""),
           "heading_err": (1.0, "rad"), "lookahead_dx": (la, "m"), "lookahead_dy": (la, "m"),
           "goal_dx": (5.0, "m"), "goal_dy": (5.0, "m"), "goal_dyaw": (1.0, "rad"), "progress": (1.0, ""),
           "partner1_dx": (2.0, "m"), "partner1_dy": (2.0, "m"), "partner1_strain": (ds, "m"),
           "partner2_dx": (2.0, "m"), "partner2_dy": (2.0, "m"), "partner2_strain": (ds, "m"),
           "wall_dist_front": (RAY_MAX, "m"), "wall_dist_left": (RAY_MAX, "m"), "wall_dist_back": (RAY_MAX, "m"),
           "wall_dist_right": (RAY_MAX, "m"), "payload_clearance": (1.0, "m"), "payload_wall_dx": (1.0, "m"),
           "payload_wall_dy": (1.0, "m"), "time_left": (1.0, "")}
    assert list(out) == OBS_FEATURE_NAMES
    return out


def observation_noise_std(cfg: EnvConfig) -> np.ndarray:
    """Per-feature std [OBS_DIM] of the additive Gaussian observation noise (in feature units).

    Derived from a localization error of ``cfg.obs_noise_xy`` (m) and ``cfg.obs_noise_yaw``
    (rad) per localized pose (each carrier, the payload): a feature relative to two
    independently localized poses (carrier -> slot/grasp/payload/partner, payload yaw
    relative to own yaw) gets sqrt(2) of it, a feature relative to one pose and the map
    (payload -> route/goal, wall distances) gets one, velocities one pose error per control
    period, and features divided by a scale get the scaled std. ``progress`` and
    ``time_left`` are exact (0). The rotation of carrier-frame vectors by the carrier's yaw
    error (|v| sigma_yaw, <= 4 mm for the 0.8 m grasp offsets) is not modelled separately.
    """
    sx, sy, r2 = cfg.obs_noise_xy, cfg.obs_noise_yaw, np.sqrt(2.0)
    v_scale = cfg.max_step_xy / cfg.control_dt
    w_scale = cfg.max_step_yaw / cfg.control_dt
    per = {
        "vel_x": sx / cfg.control_dt / v_scale, "vel_y": sx / cfg.control_dt / v_scale,
        "vel_yaw": sy / cfg.control_dt / w_scale,
        "slot_dx": r2 * sx / cfg.lookahead, "slot_dy": r2 * sx / cfg.lookahead, "slot_dyaw": r2 * sy,
        "grasp_dx": r2 * sx / cfg.drop_strain, "grasp_dy": r2 * sx / cfg.drop_strain,
        "grasp_strain": r2 * sx / cfg.drop_strain,
        "payload_dx": r2 * sx, "payload_dy": r2 * sx, "payload_sin": r2 * sy, "payload_cos": r2 * sy,
        "heading_err": sy, "lookahead_dx": sx / cfg.lookahead, "lookahead_dy": sx / cfg.lookahead,
        "goal_dx": sx / 5.0, "goal_dy": sx / 5.0, "goal_dyaw": sy, "progress": 0.0,
        "partner1_dx": r2 * sx / 2.0, "partner1_dy": r2 * sx / 2.0, "partner1_strain": r2 * sx / cfg.drop_strain,
        "partner2_dx": r2 * sx / 2.0, "partner2_dy": r2 * sx / 2.0, "partner2_strain": r2 * sx / cfg.drop_strain,
        "wall_dist_front": sx / RAY_MAX, "wall_dist_left": sx / RAY_MAX, "wall_dist_back": sx / RAY_MAX,
        "wall_dist_right": sx / RAY_MAX,
        "payload_clearance": sx, "payload_wall_dx": sx, "payload_wall_dy": sx, "time_left": 0.0,
    }
    assert set(per) == set(OBS_FEATURE_NAMES)
    return np.array([per[name] for name in OBS_FEATURE_NAMES])


@dataclass
class Snapshot:
    """Everything the task layer derives from the physics state at one instant (K envs)."""

    cxy: np.ndarray         # [K,3,2] carrier positions
    cyaw: np.ndarray        # [K,3]
    cvel: np.ndarray        # [K,3,3] world (vx, vy, wz)
    pxy: np.ndarray         # [K,2]
    pz: np.ndarray          # [K]
    pyaw: np.ndarray        # [K]
    tilt: np.ndarray        # [K] rad
    pvel: np.ndarray        # [K,6]
    strain: np.ndarray      # [K,3] m
    s: np.ndarray           # [K] route arc length of the payload projection
    look_xy: np.ndarray     # [K,2] route lookahead point
    look_yaw: np.ndarray    # [K] route heading there
    route_yaw: np.ndarray   # [K] route heading at the projection
    contact: np.ndarray     # [K] bool: any wall contact
    clearance: np.ndarray   # [K] min signed distance of the formation (payload points, carrier discs) to walls
    pay_dist: np.ndarray    # [K,P] signed distance of each payload boundary point to the nearest wall
    pay_vec: np.ndarray     # [K,P,2] vector from each payload boundary point to its nearest wall point
    car_dist: np.ndarray    # [K,3] signed distance of each carrier centre to the nearest wall

    @classmethod
    def empty(cls, K: int) -> Snapshot:
        """A snapshot of K envs to fill (``snapshot`` writes it in place)."""
        P, n = len(PAYLOAD_POINTS_LOCAL), N_CARRIERS
        return cls(cxy=np.zeros((K, n, 2)), cyaw=np.zeros((K, n)), cvel=np.zeros((K, n, 3)), pxy=np.zeros((K, 2)),
                   pz=np.zeros(K), pyaw=np.zeros(K), tilt=np.zeros(K), pvel=np.zeros((K, 6)),
                   strain=np.zeros((K, n)), s=np.zeros(K), look_xy=np.zeros((K, 2)), look_yaw=np.zeros(K),
                   route_yaw=np.zeros(K), contact=np.zeros(K, dtype=bool), clearance=np.zeros(K),
                   pay_dist=np.zeros((K, P)), pay_vec=np.zeros((K, P, 2)), car_dist=np.zeros((K, n)))

    def take(self, idx) -> "Snapshot":
        return Snapshot(**{name: getattr(self, name)[idx] for name in self.__dataclass_fields__})

    def put(self, idx, other: "Snapshot"):
        """Overwrite envs idx with another snapshot of those envs."""
        for name in self.__dataclass_fields__:
            getattr(self, name)[idx] = getattr(other, name)


def snapshot(phys: TransportPhysics, scene: SceneBatch, s_prev, goal_s, cfg: EnvConfig, out: Snapshot, envs):
    """Fill rows ``envs`` (sorted indices) of ``out`` with the snapshot of those envs in their own
    layouts (``scene``; ``s_prev``, ``goal_s`` [K]: previous route projections and goal arc
    lengths), in one kernel call; ``reference.snapshot`` is the numpy computation."""
    kernels.snapshot_rows(
        envs, phys.qpos, phys.qvel, phys.contact, phys.carrier_qadr, phys.carrier_vadr, phys.payload_qadr,
        phys.payload_vadr, scene.route_points, scene.route_s, scene.route_heading, scene.route_n, scene.route_ds,
        PROJECT_BACK, scene.route_width, s_prev, goal_s, float(cfg.lookahead), scene.tables, PAYLOAD_POINTS_LOCAL,
        GRASP_LOCAL, CARRY_HEIGHT, CARRIER_RADIUS, out.cxy, out.cyaw, out.cvel, out.pxy, out.pz, out.pyaw, out.tilt,
        out.pvel, out.strain, out.s, out.look_xy, out.look_yaw, out.route_yaw, out.contact, out.clearance,
        out.pay_dist, out.pay_vec, out.car_dist)


def slot_targets(snap: Snapshot):
    """World position [K,3,2] and yaw [K,3] of each carrier's grasp slot at the lookahead pose."""
    K = len(snap.pxy)
    slot = snap.look_xy[:, None, :] + from_frame(np.broadcast_to(GRASP_LOCAL, (K, 3, 2)), snap.look_yaw[:, None])
    return slot, snap.look_yaw[:, None] + FACING


def observe(snap: Snapshot, scene: SceneBatch, goal_xy, goal_yaw, progress, time_left, cfg: EnvConfig, envs, obs, state):
    """Rows ``envs`` of the per-carrier observations ``obs [K,3,OBS_DIM]`` (order of
    OBS_FEATURE_NAMES) and the critic's state ``state [K,STATE_DIM]`` (both float32, noise-free),
    in one kernel call; ``goal_*``, ``progress``, ``time_left`` are [K]. ``reference.observe``
    is the numpy computation."""
    human = -1 if cfg.human_slot is None else int(cfg.human_slot)
    kernels.observe_rows(
        envs, snap.cxy, snap.cyaw, snap.cvel, snap.pxy, snap.pz, snap.pyaw, snap.tilt, snap.pvel, snap.strain,
        snap.look_xy, snap.look_yaw, snap.clearance, snap.pay_dist, snap.pay_vec, goal_xy, goal_yaw, progress,
        time_left, human, scene.tables, GRASP_LOCAL, FACING, _RAY_ANGLES, cfg.max_step_xy / cfg.control_dt,
        cfg.max_step_yaw / cfg.control_dt, float(cfg.lookahead), float(cfg.drop_strain), CARRIER_RADIUS, RAY_MAX,
        CARRY_HEIGHT, obs, state)


STATE_DIM = 4 + 3 + 2 + 6 + 3 + 9 + 2 + 1 + 2 + 1 + 1 + 3 + 1 + 12 + 1 + 3
