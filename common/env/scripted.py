"""Scripted reference controller (route following with formation keeping) and scripted human.

The controller uses the true state (privileged): it asks the payload to move toward
the route lookahead pose by a bounded rigid motion (translation ``v``, rotation
``w``) and sends each carrier to where its grasp lands after that motion, which both
advances the payload and removes formation error (the carrier->grasp offset).
"""
from __future__ import annotations

import numpy as np

from common.env.config import EnvConfig
from common.env.geometry import from_frame, to_frame, wrap
from common.env.layout import FACING, GRASP_LOCAL
from common.env.observations import Snapshot
from common.spec import JOINT_ACT_DIM


def scripted_actions(snap: Snapshot, cfg: EnvConfig, speed: float = 0.85, max_turn: float = 0.05,
                     aim_offset: float = 0.0):
    """Stacked actions [K,9] in [-1,1] of the reference controller. ``aim_offset`` (m) moves its aim
    point sideways, to the left of the route's lookahead heading: a biased controller that tracks
    a line ``aim_offset`` off the route (the calibration's "aimed 0.2 m off the route")."""
    K = len(snap.pxy)
    look_xy = snap.look_xy
    if aim_offset:
        look_xy = look_xy + aim_offset * np.stack([-np.sin(snap.look_yaw), np.cos(snap.look_yaw)], axis=1)
    e = look_xy - snap.pxy
    dist = np.linalg.norm(e, axis=1, keepdims=True)
    v = e * np.minimum(1.0, speed * cfg.max_step_xy / np.maximum(dist, 1e-9))
    w = np.clip(wrap(snap.look_yaw - snap.pyaw), -max_turn, max_turn)
    # keep every grasp's rigid displacement within the per-step budget
    r = from_frame(np.broadcast_to(GRASP_LOCAL, (K, 3, 2)), snap.pyaw[:, None])
    disp = v[:, None, :] + w[:, None, None] * np.stack([-r[..., 1], r[..., 0]], -1)
    scale = np.minimum(1.0, speed * cfg.max_step_xy / np.maximum(np.linalg.norm(disp, axis=-1).max(axis=1), 1e-9))
    v, w = v * scale[:, None], w * scale
    new_yaw = snap.pyaw + w
    slot = (snap.pxy + v)[:, None, :] + from_frame(np.broadcast_to(GRASP_LOCAL, (K, 3, 2)), new_yaw[:, None])
    step = slot - snap.cxy
    a_xy = to_frame(step, snap.cyaw) / cfg.max_step_xy
    n = np.linalg.norm(a_xy, axis=-1, keepdims=True)
    a_xy = a_xy / np.maximum(n, 1.0)
    a_yaw = np.clip(wrap(new_yaw[:, None] + FACING - snap.cyaw) / cfg.max_step_yaw, -1.0, 1.0)
    return np.concatenate([a_xy, a_yaw[..., None]], axis=-1).reshape(K, JOINT_ACT_DIM)


class ScriptedHuman:
    """Human partner in one slot: the reference controller's command for that slot,
    delayed by ``delay`` control steps, plus Gaussian noise, clipped to [-1,1]."""

    def __init__(self, slot: int, cfg: EnvConfig, num_envs: int):
        self.slot, self.cfg, self.K = slot, cfg, num_envs
        self.queue = np.zeros((num_envs, cfg.human_delay + 1, 3))

    def reset(self, k: int, snap_action):
        self.queue[k] = snap_action[k, 3 * self.slot:3 * self.slot + 3]

    def act(self, intended, rngs):
        """Push this step's intended command [K,9]; return the executed human block [K,3]."""
        self.queue[:, :-1] = self.queue[:, 1:]
        self.queue[:, -1] = intended[:, 3 * self.slot:3 * self.slot + 3]
        noise = np.stack([rng.normal(0.0, self.cfg.human_noise, 3) for rng in rngs])
        return np.clip(self.queue[:, 0] + noise, -1.0, 1.0)
