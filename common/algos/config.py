"""Learner configuration: the one source of defaults for all five methods."""
from __future__ import annotations

import math
from dataclasses import asdict, dataclass

from common.config_fields import bounded, check_fields, from_mapping


@dataclass
class AlgoConfig:
    # optimisation
    # Few large minibatches (an update's cost is per-minibatch overhead) and lr 1e-3 (the leaf
    # controllers must move within a short budget): measured in docs/results_narrow_gate.md.
    actor_lr: float = bounded(1e-3, gt=0.0, le=1.0)
    critic_lr: float = bounded(1e-3, gt=0.0, le=1.0)
    epochs: int = bounded(4, ge=1, le=1000)
    minibatches: int = bounded(2, ge=1, le=4096)
    clip: float = bounded(0.2, gt=0.0, le=1.0)                # epsilon_clip of Eq. (ppo_surrogates)
    gamma: float = bounded(0.99, gt=0.0, le=1.0)
    gae_lambda: float = bounded(0.95, ge=0.0, le=1.0)
    ent_coef: float = bounded(1e-3, ge=0.0, le=100.0)           # bonus on the proposal entropy (log_std)
    vf_coef: float = bounded(1.0, ge=0.0, le=1e3)             # scales the critic loss (own optimizer)
    max_grad_norm: float = bounded(10.0, gt=0.0, le=1e6)
    normalize_advantages: bool = True
    # TALO, Eq. (talo_projection)
    talo_sigma: float = bounded(1.0, ge=0.0, le=1e6)
    talo_eps: float = bounded(1e-8, ge=0.0, le=1.0)
    # How the joint methods (talo_cbf, sage, joint_cbf) apply their direction g:
    #   "adam":   -g is handed to the per-carrier Adams after global norm clipping
    #             (max_grad_norm); the entropy gradient is added after the projection.
    #             Adam's per-coordinate rescaling means the applied step need not meet
    #             Eq. (talo_condition) (learner metric talo_condition_met).
    #   "direct": theta <- theta + talo_eta * g (the paper's update after Eq. talo_projection),
    #             no clipping; the entropy gradient is folded into g_ind *before* the
    #             projection, so the applied step itself meets Eq. (talo_condition).
    # Default "adam": scale-free, it raised the reward more than the direct step on the
    # synthetic bandit, though only the direct step meets the condition on every step
    # (docs/results_talo_step.md).
    talo_step: str = bounded("adam", choices=("adam", "direct"))
    # eta_theta of the direct step: between the values that learned too slowly and those that
    # blew W_gap up on the bandit (docs/results_talo_step.md).
    talo_eta: float = bounded(0.05, gt=0.0, le=10.0)
    # HAPPO carrier order: "update" (drawn once per update, as HARL draws it once per
    # training call) or "minibatch" (redrawn every minibatch; the old behaviour)
    happo_order: str = bounded("update", choices=("update", "minibatch"))
    # learner diagnostics: QP solves of a_ST (correction_st) on this many evenly
    # spaced samples per update (0: off)
    diag_qp_samples: int = bounded(256, ge=0, le=65536)
    # the local claim's A/B (Method.local_ab): every mech_ab_every-th update (0: off), on
    # its last minibatch, W_gap after a step of length mech_ab_step along g_TALO and along
    # g_ind (0.0: the length of the step the method itself took on that minibatch)
    mech_ab_every: int = bounded(1, ge=0, le=10**6)
    mech_ab_step: float = bounded(0.0, ge=0.0, le=10.0)
    # schedules over training progress p in [0, 1] (geometric interpolation)
    tau_start: float = bounded(1.0, gt=0.0, le=100.0)           # ST backward temperature, Eq. (st_gate)
    tau_end: float = bounded(0.1, gt=0.0, le=100.0)
    kappa_start: float = bounded(1.0, gt=0.0, le=1e6)         # SAIL penalty, Eq. (sail_projection)
    kappa_end: float = bounded(30.0, gt=0.0, le=1e6)
    # learner-side SAIL gradient: "implicit" (Eq. sail_jacobian at the actors'
    # converged center, one solve) or "unrolled" (differentiate every Newton step)
    sail_grad: str = bounded("implicit", choices=("implicit", "unrolled"))
    # critic, Eq. (team_context)
    critic_hidden: int = bounded(128, ge=1, le=4096)
    encoder_latent: int = bounded(32, ge=1, le=1024)
    critic_uses_state: bool = False   # append the env's global state to V's input
    # trees
    tree_depth: int = bounded(4, ge=1, le=12)    # 2^depth leaves per carrier
    init_log_std: float = bounded(-0.5, ge=-10.0, le=2.0)
    # sparse trees (common/policy/tree.py TreeConfig): at most split_k features per split,
    # leaf_k per leaf gain row; 0 = dense. One feature per split: every predicate is one
    # threshold in physical units, at no measured cost (docs/results_sparse_trees.md).
    split_k: int = bounded(1, ge=0, le=4096)
    leaf_k: int = bounded(0, ge=0, le=4096)
    seed: int = bounded(0, ge=0, le=2**31 - 1)

    def __post_init__(self) -> None:
        self.validate()

    def validate(self, prefix: str = "AlgoConfig.") -> None:
        """Types, finiteness and each field's range (``bounded``); a ``ValueError`` naming the field."""
        check_fields(self, prefix)

    def to_dict(self) -> dict:
        return asdict(self)

    @classmethod
    def from_dict(cls, d: dict) -> "AlgoConfig":
        return from_mapping(cls, d)


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
