"""Configuration of the three-carrier transport environment (one source of
defaults). The team's physical layout (payload, grasps, carrier size) is in
``common/env/layout.py``; the scenarios in ``common/env/scenarios.py``.
"""
from __future__ import annotations

from dataclasses import dataclass, field

from common.config_fields import bounded, check_fields
from common.env.scenarios import SCENARIOS
from common.spec import N_CARRIERS


@dataclass(frozen=True)
class RewardWeights:
    """Shared team reward, one term per line (see common/env/task.py: team_reward)."""

    progress: float = bounded(1.0, ge=-1e3, le=1e3)     # route progress per step, in units of max_step_xy
    heading: float = bounded(0.1, ge=-1e3, le=1e3)      # x |payload heading error w.r.t. route tangent| (rad)
    strain: float = bounded(0.5, ge=-1e3, le=1e3)       # x mean (grasp strain / drop threshold)^2
    collision: float = bounded(1.0, ge=-1e3, le=1e3)    # per control step with any wall contact
    drop: float = bounded(10.0, ge=-1e3, le=1e3)        # once, when the grasp is released
    time: float = bounded(0.01, ge=-1e3, le=1e3)        # per step
    success: float = bounded(10.0, ge=-1e3, le=1e3)     # once, on reaching the goal pose


@dataclass
class EnvConfig:
    """Environment options; ``max_steps=None`` uses the scenario's own time limit."""

    scenario: str = bounded("narrow_gate", choices=sorted(SCENARIOS))
    human_slot: int | None = bounded(None, ge=0, lt=N_CARRIERS)       # carrier slot played by the scripted human
    max_steps: int | None = bounded(None, ge=1, le=10**6)
    # control: carrier i's action a_i in [-1,1]^3 moves its base target by
    # R(psi_i) [dx, dy] * max_step_xy and dpsi * max_step_yaw (own frame)
    control_dt: float = bounded(0.1, gt=0.0, le=1.0)
    substeps: int = bounded(10, ge=1, le=1000)                  # physics steps of timestep control_dt/substeps
    max_step_xy: float = bounded(0.08, gt=0.0, le=1.0)           # m per control step
    max_step_yaw: float = bounded(0.1, gt=0.0, le=3.2)           # rad per control step
    # frozen low-level tracker (position actuators with velocity feedback)
    carrier_mass: float = bounded(60.0, gt=0.0, le=1e4)              # heavy base: the tracker dominates the grasp forces
    kp_xy: float = bounded(120000.0, gt=0.0, le=1e8)             # ~44 rad/s: ~93% of a step is realized in control_dt
    kp_yaw: float = bounded(4000.0, gt=0.0, le=1e8)
    target_leash: float = bounded(0.04, gt=0.0, le=1.0)          # m the tracker target may lead the measured pose
    # soft grasp (equality connect) and release
    grasp_solref: tuple[float, float] = (0.04, 1.0)
    grasp_solimp: tuple[float, float, float] = (0.3, 0.3, 0.001)  # soft: ~6 mm sag, strain builds under inconsistent commands
    drop_strain: float = bounded(0.2, gt=0.0, le=2.0)            # m of anchor separation that releases the grasp
    # task
    lookahead: float = bounded(0.6, gt=0.0, le=10.0)              # m of route lookahead for observations
    goal_pos_tol: float = bounded(0.25, gt=0.0, le=10.0)          # m
    goal_yaw_tol: float = bounded(0.2, gt=0.0, le=3.2)           # rad
    randomize: bool = True               # episode randomization: start, goal, payload mass, obs noise
    # --- graded outcomes (deployment-realistic variation; all applied only when randomize=True,
    # so randomize=False is a fully deterministic episode: nominal start, farthest goal, nominal
    # mass, noise-free observations). Every draw comes from the env's seeded per-env RNGs.
    # Start pose: uniform in the scenario's start_range box (+-x along the route, +-y across it,
    # +-yaw) scaled by start_spread. The team is walked into its staging area by a human, not
    # placed on marks: 1.5 x the scenario boxes is a +-22-30 cm along-route, +-30-53 cm lateral
    # and +-17-39 deg yaw placement error, what eye-balling a 1.6 m board into a 2.3-4.4 m wide
    # room or corridor gives. A start whose formation footprint (board + carrier discs) is closer than
    # start_min_clearance to a wall is redrawn (2x the shield's 5 cm margins, so the first safety
    # rows hold at t=0 and no run starts in contact); 1.0 is the original box.
    start_spread: float = bounded(1.5, ge=0.0, le=10.0)
    start_min_clearance: float = bounded(0.1, ge=0.0, le=2.0)    # m
    # Layout per episode (common/env/scenarios.py, each scenario's builder docstring): every layout
    # parameter (gate positions and openings, corridor widths and turn points, obstacle offsets,
    # start and goal marks) uniform in nominal +- layout_spread x its stated half-range, drawn from
    # the env's layout stream (train or eval, common/env/scene.py). 1.0: the stated spreads (what
    # rooms of each kind vary by; calibrated with the scripted controller, docs/protocol/calibration.md);
    # 0.0: the nominal layout every episode (the scenarios before issue 29). Applied only when randomize.
    layout_spread: float = bounded(1.0, ge=0.0, le=2.0)   # a scale of the stated spreads
    # Payload mass per episode, uniform (kg): the 10 kg board (layout.PAYLOAD_MASS) with a +-10%
    # material tolerance (plywood/MDF density) plus 0-1 kg of fixtures (grasp handles, clamps,
    # markers) -> 9-12 kg. Set exactly per env (each env gets its own MjModel copy whose payload
    # body mass and inertia are scaled, common/env/physics.py: set_payload_mass); the frozen
    # tracker's gains stay tuned for the nominal 10 kg, as on the real robots.
    payload_mass_range: tuple[float, float] = bounded((9.0, 12.0), gt=0.0, le=1e3)
    # Observation noise: additive zero-mean Gaussian on the features the trees see, derived
    # from a localization/odometry error of obs_noise_xy (m) and obs_noise_yaw (rad) per pose
    # (observations.observation_noise_std lists the per-feature std). 5 mm / 0.3 deg is what
    # wheel odometry fused with a motion-capture or lidar fix gives over a 10 m run. The critic's
    # state and the safety rows (C, c) use the true simulator state: the shield is modelled as
    # exact on its own measured state (the CBF-QP's guarantee is about that state), the
    # noise only perturbs the trees' decisions.
    obs_noise_xy: float = bounded(0.005, ge=0.0, le=1.0)         # m
    obs_noise_yaw: float = bounded(0.005, ge=0.0, le=3.2)        # rad (~0.3 deg)
    # Actuation delay in control steps (applied whether or not randomize is set): the robots
    # execute the (shielded) action sent action_delay_steps steps earlier; zeros fill the queue at
    # reset. 0: the 100 ms control period absorbs the whole-body controller's latency (default);
    # 1: a 100 ms comm/actuation latency, a robustness setting (the one-step CBF then certifies an
    # action for a state one step older than the one it is executed in). The human's block has
    # its own reaction delay (human_delay) and is not delayed again.
    action_delay_steps: int = bounded(0, ge=0, le=100)
    reward: RewardWeights = field(default_factory=RewardWeights)
    # safety rows (common/env/safety.py)
    max_rows: int = bounded(34, ge=1, le=1024)
    alpha: float = bounded(0.3, gt=0.0, le=1.0)                  # discrete CBF rate
    grasp_tol: float = bounded(0.05, gt=0.0, le=1.0)             # m of pair-distance deviation the formation rows allow (drop at drop_strain)
    # Row profile (common/env/safety.py docstring): "paper" = collision rows only (carrier-wall,
    # payload-wall; a payload drop is a task outcome the shield does not prevent); "grasp" adds
    # the formation rows (pair distances within +-grasp_tol; our extension, not in the paper).
    safety_rows: str = bounded("paper", choices=("paper", "grasp"))
    # --- outcome metrics (episode records, common/env/metrics.py) ---
    # A margin violation (margin_violation_steps, margin_col_per_1k) is a true barrier of the
    # shield's specification below -margin_violation_tol. 5 mm: what carriers of this kind
    # resolve and place to (localization 5 mm, obs_noise_xy; the frozen tracker realizes a
    # commanded base step to millimetres), so a barrier of -5e-8 m (the shielded runs'
    # median, a QP at its row's boundary with the one-step predictor's rounding) is no
    # measurable excursion; 0.0 counts every one.
    margin_violation_tol: float = bounded(0.005, ge=0.0, le=1.0)   # m
    # A truncated episode (time limit, neither success nor drop) is a deadlock when the payload
    # stayed within deadlock_move_xy and deadlock_move_yaw of one pose for its last
    # deadlock_window_s (the team stopped: e.g. its proposals held at a gate by the shield),
    # else a timeout (still moving, too slowly or the wrong way). A moving team leaves that
    # neighbourhood within a step or two (max_step_xy 8 cm, max_step_yaw 0.1 rad per 0.1 s).
    deadlock_window_s: float = bounded(5.0, gt=0.0, le=1e4)       # s
    deadlock_move_xy: float = bounded(0.05, ge=0.0, le=10.0)      # m
    deadlock_move_yaw: float = bounded(0.1, ge=0.0, le=3.2)       # rad
    # scripted human partner (human_slot)
    human_noise: float = bounded(0.15, ge=0.0, le=10.0)           # std of additive action noise
    human_delay: int = bounded(2, ge=0, le=100)                # control steps of reaction delay

    def __post_init__(self):
        self.validate()

    def validate(self, prefix: str = "") -> None:
        """Types, finiteness and each field's range (``bounded``); a ``ValueError`` naming the field."""
        check_fields(self, prefix)
        lo, hi = self.payload_mass_range
        if not lo <= hi:
            raise ValueError(f"{prefix}payload_mass_range must be (lo, hi) with lo <= hi, got {self.payload_mass_range}")

    @property
    def timestep(self) -> float:
        return self.control_dt / self.substeps

    @property
    def episode_steps(self) -> int:
        return self.max_steps if self.max_steps is not None else SCENARIOS[self.scenario].max_steps
