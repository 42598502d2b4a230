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
    # How the joint methods (talo_cbf, sage, joint_cbf) apply their direction g:
    #   "adam":   -g is handed to the per-carrier Adams after global norm clipping
    #             (max_grad_norm); the entropy gradient is added after the projection.
    #             Adam's per-coordinate rescaling means the applied step need not meet
    #             Eq. (talo_condition) (learner metric talo_condition_met).
    #   "direct": theta <- theta + talo_eta * g (the paper's update after Eq. talo_projection),
    #             no clipping; the entropy gradient is folded into g_ind *before* the
    #             projection, so the applied step itself meets Eq. (talo_condition).
    # Default "adam": on the synthetic bandit (obs_dim 40, 512 samples/update, 40 updates,
    # 2 seeds) adam raised the deterministic reward more (talo_cbf +1.57 vs +1.41 at
    # eta 0.05; sage +1.43 vs +1.21) and is scale-free, while the direct step met the
    # condition on every minibatch (adam: talo_cbf 81%, sage 98%) but needs eta tuned to
    # the gradient scale, which grew during training (eta 0.1: talo_cbf's W_gap averaged
    # ~600 over 40 updates).
    talo_step: str = "adam"
    # eta_theta of the direct step, from {0.02, 0.05, 0.1, 0.2} on that bandit: 0.02 learned
    # slowest, 0.1 let W_gap blow up over 40 updates, 0.2 made a seed's reward fall within 20.
    # Its steps are about 2x Adam's (actor_lr=1e-3) in parameter norm.
    talo_eta: float = 0.05
    # HAPPO carrier order: "update" (drawn once per update, as HARL draws it once per
    # training call) or "minibatch" (redrawn every minibatch; the old behaviour)
    happo_order: str = "update"
    # learner diagnostics: QP solves of a_ST (correction_st) on this many evenly
    # spaced samples per update (0: off)
    diag_qp_samples: int = 256
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
    # sparse trees (common/policy/tree.py TreeConfig): at most split_k features per split,
    # leaf_k per leaf gain row; 0 = dense. One feature per split: every predicate is one
    # threshold in physical units, at no measured cost (docs/results_sparse_trees.md).
    split_k: int = 1
    leaf_k: int = 0
    seed: int = 0

    def __post_init__(self) -> None:
        positive = ("actor_lr", "critic_lr", "clip", "max_grad_norm", "tau_start", "tau_end",
                    "kappa_start", "kappa_end", "talo_eta")
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
        if self.talo_step not in ("adam", "direct"):
            raise ValueError(f"AlgoConfig.talo_step must be 'adam' or 'direct' (got {self.talo_step!r})")
        if self.happo_order not in ("update", "minibatch"):
            raise ValueError(f"AlgoConfig.happo_order must be 'update' or 'minibatch' (got {self.happo_order!r})")
        if int(self.split_k) < 0 or int(self.leaf_k) < 0:
            raise ValueError(f"AlgoConfig.split_k and leaf_k must be >= 0, 0 = dense (got {self.split_k}, {self.leaf_k})")
        if int(self.diag_qp_samples) < 0:
            raise ValueError(f"AlgoConfig.diag_qp_samples must be >= 0 (got {self.diag_qp_samples})")
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
