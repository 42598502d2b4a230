"""The transport task, apart from its physics (as dm_control separates Task
from Physics): what a step's snapshot means for the team, i.e. the shared
reward, success, drop, and termination vs truncation. Pure functions of the
measured snapshot (``common.env.observations.Snapshot``) and the config.

Reward (weights in ``RewardWeights``), per control step:

    r = w_p ds / max_step_xy - w_h |heading err| - w_s mean((strain / drop_strain)^2)
        - w_c collision - w_d drop - w_t + w_succ success

where ``ds`` is the route progress of the payload projection this step
(clipped to [-2, 2] max steps) and ``collision`` is any wall contact.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from common.env import kernels
from common.env.config import EnvConfig
from common.env.geometry import wrap


@dataclass
class StepOutcome:
    """Per-env outcome of one control step, all [K]."""

    reward: np.ndarray
    success: np.ndarray       # goal pose reached with the payload held
    drop: np.ndarray          # grasp released: the strain exceeded drop_strain
    terminated: np.ndarray    # success or drop
    truncated: np.ndarray     # time limit, not terminated
    collision: np.ndarray     # any wall contact this step
    heading_error: np.ndarray # |route tangent - payload yaw| (rad)


def step_outcome(snap, s_old: np.ndarray, t: np.ndarray, max_steps: int, goal_xy: np.ndarray,
                 goal_yaw: np.ndarray, cfg: EnvConfig) -> StepOutcome:
    """The outcome of the step that led to ``snap`` (``s_old`` [K]: the route projection before it,
    ``t`` [K]: steps taken including it), in one kernel call; ``reference.step_outcome`` is
    the numpy computation."""
    K, w = len(s_old), cfg.reward
    (reward, heading_error), flags = np.empty((2, K)), np.empty((5, K), bool)
    o = StepOutcome(reward=reward, success=flags[0], drop=flags[1], terminated=flags[2], truncated=flags[3],
                    collision=flags[4], heading_error=heading_error)
    o.collision[:] = snap.contact
    kernels.step_outcome_rows(
        snap.strain, snap.pxy, snap.pyaw, snap.route_yaw, snap.s, snap.contact, s_old, t, max_steps, goal_xy,
        goal_yaw, cfg.drop_strain, cfg.goal_pos_tol, cfg.goal_yaw_tol, cfg.max_step_xy, w.progress, w.heading,
        w.strain, w.collision, w.drop, w.time, w.success, o.reward, o.success, o.drop, o.terminated, o.truncated,
        o.heading_error)
    return o


class StillnessClock:
    """Per env, the payload pose it was last still at and the step it got there: an
    episode that times out with the payload still for the last ``deadlock_window_s``
    (within ``deadlock_move_xy`` / ``deadlock_move_yaw``) ended in deadlock, not slowness."""

    def __init__(self, cfg: EnvConfig, num_envs: int):
        self.cfg = cfg
        self.pose = np.zeros((num_envs, 3))
        self.since = np.zeros(num_envs, dtype=np.int64)

    def restart(self, envs, pxy: np.ndarray, pyaw: np.ndarray) -> None:
        """Episode start of ``envs`` at payload pose (pxy, pyaw) [len(envs)]."""
        self.pose[envs, :2], self.pose[envs, 2] = pxy, pyaw
        self.since[envs] = 0

    def update(self, pxy: np.ndarray, pyaw: np.ndarray, t: np.ndarray) -> None:
        """Restart the clock of envs whose payload left the neighbourhood of its still pose."""
        moved = ((np.hypot(pxy[:, 0] - self.pose[:, 0], pxy[:, 1] - self.pose[:, 1]) > self.cfg.deadlock_move_xy)
                 | (np.abs(wrap(pyaw - self.pose[:, 2])) > self.cfg.deadlock_move_yaw))
        if moved.any():
            self.pose[moved, :2], self.pose[moved, 2] = pxy[moved], pyaw[moved]
            self.since[moved] = t[moved]

    def deadlocked(self, k: int, steps: int) -> bool:
        """Env ``k``'s payload has been still for the window at step ``steps``."""
        return (steps - int(self.since[k])) * self.cfg.control_dt >= self.cfg.deadlock_window_s - 1e-9
