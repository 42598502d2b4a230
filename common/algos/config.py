"""Learner configuration: the one source of defaults for all five methods."""
from __future__ import annotations

import math
from dataclasses import asdict, dataclass, fields


@dataclass
class AlgoConfig:
    # optimisation
    # Tuned on narrow_gate, 2 cores (docs/results_narrow_gate.md): the update cost is
    # dominated by per-minibatch overhead (autograd calls, TALO HVP), so few large minibatches;
    # 1e-3 lets the leaf controllers move within a 4-minute budget.
    actor_lr: float = 1e-3
    critic_lr: float = 1e-3
    epochs: int = 4
    minibatches: int = 2
    clip: float = 0.2                 # epsilon_clip of Eq. (ppo_surrogates)
    gamma: float = 0.99
    gae_lambda: float = 0.95
    ent_coef: float = 1e-3            # bonus on the proposal entropy (log_std)
    vf_coef: float = 1.0              # scales the critic loss (own optimizer)
    max_grad_norm: float = 10.0
    normalize_advantages: bool = True
    # TALO, Eq. (talo_projection)
    talo_sigma: float = 1.0
    talo_eps: float = 1e-8
    # schedules over training progress p in [0, 1] (geometric interpolation)
    tau_start: float = 1.0            # ST backward temperature, Eq. (st_gate)
    tau_end: float = 0.1
    kappa_start: float = 1.0          # SAIL penalty, Eq. (sail_projection)
    kappa_end: float = 30.0
    # learner-side SAIL gradient: "implicit" (Eq. sail_jacobian at the actors'
    # converged center, one solve) or "unrolled" (differentiate every Newton step)
    sail_grad: str = "implicit"
    # critic, Eq. (team_context)
    critic_hidden: int = 128
    encoder_latent: int = 32
    critic_uses_state: bool = False   # append the env's global state to V's input
    # trees
    tree_depth: int = 4
    init_log_std: float = -0.5
    seed: int = 0

    def __post_init__(self) -> None:
        positive = ("actor_lr", "critic_lr", "clip", "max_grad_norm", "tau_start", "tau_end",
                    "kappa_start", "kappa_end")
        for name in positive:
            if not getattr(self, name) > 0:
                raise ValueError(f"AlgoConfig.{name} must be > 0 (got {getattr(self, name)})")
        for name in ("epochs", "minibatches", "tree_depth", "critic_hidden",
                     "encoder_latent"):
            if int(getattr(self, name)) < 1:
                raise ValueError(f"AlgoConfig.{name} must be >= 1 (got {getattr(self, name)})")
        if not (0 < self.gamma <= 1 and 0 <= self.gae_lambda <= 1):
            raise ValueError("AlgoConfig needs 0 < gamma <= 1 and 0 <= gae_lambda <= 1")
        if self.sail_grad not in ("implicit", "unrolled"):
            raise ValueError(f"AlgoConfig.sail_grad must be 'implicit' or 'unrolled' (got {self.sail_grad!r})")
        if self.talo_sigma < 0 or self.talo_eps < 0 or self.ent_coef < 0:
            raise ValueError("AlgoConfig.talo_sigma, talo_eps and ent_coef must be >= 0")

    def to_dict(self) -> dict:
        return asdict(self)

    @classmethod
    def from_dict(cls, d: dict) -> "AlgoConfig":
        known = {f.name for f in fields(cls)}
        unknown = set(d) - known
        if unknown:
            raise ValueError(f"unknown AlgoConfig keys: {sorted(unknown)}")
        return cls(**d)


def geometric(start: float, end: float, progress: float) -> float:
    """start^(1-p) * end^p with p clipped to [0, 1]."""
    p = min(max(float(progress), 0.0), 1.0)
    return math.exp((1.0 - p) * math.log(start) + p * math.log(end))


def tau_schedule(cfg: AlgoConfig, progress: float) -> float:
    """ST temperature: annealed geometrically tau_start -> tau_end (Eq. st_gate)."""
    return geometric(cfg.tau_start, cfg.tau_end, progress)


def kappa_schedule(cfg: AlgoConfig, progress: float) -> float:
    """SAIL penalty: raised geometrically kappa_start -> kappa_end (Eq. sail_projection)."""
    return geometric(cfg.kappa_start, cfg.kappa_end, progress)
