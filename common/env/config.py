"""Configuration of the three-carrier transport environment (one source of defaults).

Physical layout (payload frame, x along the long axis, metres):

* payload: a ``1.6 x 0.8 x 0.04`` board of ``10 kg`` carried at ``0.8 m``;
* carrier 0 grasps the front short-end midpoint ``(+0.8, 0)``, carrier 1 the back
  short-end midpoint ``(-0.8, 0)``, carrier 2 the right long-edge midpoint ``(0, -0.4)``
  (three non-collinear grasps);
* each carrier is a planar holonomic base (slide x, slide y, hinge yaw) of radius
  ``0.25 m`` whose grasp anchor lies on its yaw axis, facing the payload centre.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

N_CARRIERS = 3
ACT_DIM = 3

PAYLOAD_HALF = (0.8, 0.4, 0.02)  # board half-sizes (x, y, z)
PAYLOAD_MASS = 10.0
CARRY_HEIGHT = 0.8
CARRIER_RADIUS = 0.25
# grasp points in the payload frame; carrier i holds GRASP_LOCAL[i]
GRASP_LOCAL = np.array([[0.8, 0.0], [-0.8, 0.0], [0.0, -0.4]])
# carrier yaw relative to the payload when in formation: each faces the payload centre
FACING = np.array([math.pi, 0.0, math.pi / 2])
# Spacing of the payload boundary points. A wall corner can slip between two
# points by at most half the spacing (90-degree corner), so the spacing must stay
# below 2 * SafetyConfig.payload_margin (0.05 m) for the payload-wall rows to
# keep thin gate posts out of the board's edges. With the first sampling
# (corners and edge midpoints, 0.8 m apart) a 0.2 m gate post passed between
# the points and shielded policies scraped the payload along it.
PAYLOAD_POINT_SPACING = 0.08


def perimeter_points(half_x: float, half_y: float, spacing: float) -> np.ndarray:
    """Points around a rectangle's boundary, corners included, at most ``spacing`` apart."""
    corners = np.array([[half_x, half_y], [-half_x, half_y], [-half_x, -half_y], [half_x, -half_y]])
    pts = []
    for a, b in zip(corners, np.roll(corners, -1, axis=0)):
        n = max(1, int(math.ceil(np.linalg.norm(b - a) / spacing - 1e-9)))
        pts += [a + (b - a) * t for t in np.arange(n) / n]
    return np.array(pts)


# payload boundary points for clearance and safety rows
PAYLOAD_POINTS_LOCAL = perimeter_points(0.8, 0.4, PAYLOAD_POINT_SPACING)
# pairs (0,1), (0,2), (1,2) as in common/env/safety.py
PAIRS = ((0, 1), (0, 2), (1, 2))
PAIR_REST = np.array([np.linalg.norm(GRASP_LOCAL[i] - GRASP_LOCAL[j]) for i, j in PAIRS])
# the formation footprint (board + carrier discs) is centred at y = -0.125 in the payload
# frame; scenario routes pass gates with this lateral shift so the footprint is centred
FOOTPRINT_SHIFT = 0.125


@dataclass(frozen=True)
class RewardWeights:
    """Shared team reward, one term per line (see common/env/task.py:reward)."""

    progress: float = 1.0      # route progress per step, in units of max_step_xy
    heading: float = 0.1       # x |payload heading error w.r.t. route tangent| (rad)
    strain: float = 0.5        # x mean (grasp strain / drop threshold)^2
    collision: float = 1.0     # per control step with any wall contact
    drop: float = 10.0         # once, when the grasp is released
    time: float = 0.01         # per step
    success: float = 10.0      # once, on reaching the goal pose


@dataclass
class EnvConfig:
    """Environment options; ``max_steps=None`` uses the scenario's own time limit."""

    scenario: str = "narrow_gate"
    human_slot: int | None = None        # carrier slot played by the scripted human
    max_steps: int | None = None
    # control: carrier i's action a_i in [-1,1]^3 moves its base target by
    # R(psi_i) [dx, dy] * max_step_xy and dpsi * max_step_yaw (own frame)
    control_dt: float = 0.1
    substeps: int = 10                   # physics steps of timestep control_dt/substeps
    max_step_xy: float = 0.08            # m per control step
    max_step_yaw: float = 0.1            # rad per control step
    # frozen low-level tracker (position actuators with velocity feedback)
    carrier_mass: float = 60.0               # heavy base: the tracker dominates the grasp forces
    kp_xy: float = 120000.0              # ~44 rad/s: ~93% of a step is realized in control_dt
    kp_yaw: float = 4000.0
    target_leash: float = 0.04           # m the tracker target may lead the measured pose
    # soft grasp (equality connect) and release
    grasp_solref: tuple[float, float] = (0.04, 1.0)
    grasp_solimp: tuple[float, float, float] = (0.3, 0.3, 0.001)  # soft: ~6 mm sag, strain builds under inconsistent commands
    drop_strain: float = 0.2             # m of anchor separation that releases the grasp
    # task
    lookahead: float = 0.6               # m of route lookahead for observations
    goal_pos_tol: float = 0.25           # m
    goal_yaw_tol: float = 0.2            # rad
    randomize: bool = True               # start/goal randomization within scenario ranges
    reward: RewardWeights = field(default_factory=RewardWeights)
    # safety rows (common/env/safety.py)
    max_rows: int = 34
    alpha: float = 0.3                   # discrete CBF rate
    grasp_tol: float = 0.05              # m of pair-distance deviation the formation rows allow (drop at drop_strain)
    # scripted human partner (human_slot)
    human_noise: float = 0.15            # std of additive action noise
    human_delay: int = 2                 # control steps of reaction delay

    def __post_init__(self):
        from common.env.scenarios import SCENARIOS

        if self.scenario not in SCENARIOS:
            raise ValueError(f"unknown scenario {self.scenario!r}; choose from {sorted(SCENARIOS)}")
        if self.human_slot is not None and self.human_slot not in range(N_CARRIERS):
            raise ValueError(f"human_slot must be None or 0..{N_CARRIERS - 1}, got {self.human_slot}")
        if self.substeps < 1 or self.control_dt <= 0:
            raise ValueError("substeps must be >= 1 and control_dt > 0")
        if self.max_steps is not None and self.max_steps < 1:
            raise ValueError("max_steps must be positive")
        if self.human_delay < 0:
            raise ValueError("human_delay must be >= 0")

    @property
    def timestep(self) -> float:
        return self.control_dt / self.substeps

    @property
    def episode_steps(self) -> int:
        from common.env.scenarios import SCENARIOS

        return self.max_steps if self.max_steps is not None else SCENARIOS[self.scenario].max_steps
