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
