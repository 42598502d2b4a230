"""Configuration of the three-carrier transport environment (one source of
defaults). The team's physical layout (payload, grasps, carrier size) is in
``common/env/layout.py``; the scenarios in ``common/env/scenarios.py``.
"""
from __future__ import annotations

from dataclasses import dataclass, field

from common.env.scenarios import SCENARIOS
from common.spec import N_CARRIERS


@dataclass(frozen=True)
class RewardWeights:
    """Shared team reward, one term per line (see common/env/task.py: team_reward)."""

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
        return self.max_steps if self.max_steps is not None else SCENARIOS[self.scenario].max_steps
