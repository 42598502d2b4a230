"""Batch preparation: a rollout batch (the chunk schema, docs/interfaces.md) checked,
its values bootstrapped by the critic, GAE advantages and returns (Eq. team_context's
V), and the flat torch ``Minibatch`` the update steps read; plus the whole-batch
action diagnostics (numpy, no QP).

The likelihood is always the proposal density at the stored ``a_prop`` (Eq. action_chain):
the batch carries ``a_prop`` and the actors' ``logp`` of it, the behaviour policy's.
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from common.algos.config import AlgoConfig
from common.algos.critic import TeamCritic, ValueNormalizer, compute_gae, next_values
from common.policy.proposal import density_terms
from common.policy.sail import sail_rows_np
from common.safety_rows import VIOLATION_TOL, SafetyRows
from common.spec import CARRIER_ACT_DIM
from common.wire import SCHEMAS

ROW_KINDS = ("carrier_wall", "payload_wall", "formation")   # common.env.safety row kinds 0, 1, 2

# Batch arrays the learner always reads; their shapes are the chunk schema's
# (common/wire.py SCHEMAS["traj"]). "final_obs" is needed only where some step is truncated.
REQUIRED = ("obs", "C", "c", "row_mask", "fixed_mask", "a_st", "a_prop", "a_exec", "logp",
            "reward", "terminated", "truncated")


@dataclass
class Minibatch:
    """Flat torch views of one minibatch (B samples)."""
    obs: Tensor        # [B, N, O]
    state: Tensor      # [B, S]
    C: Tensor          # [B, M, D]
    c: Tensor          # [B, M]
    row_mask: Tensor   # [B, M] bool
    fixed: Tensor      # [B, D] bool
    a_prop: Tensor     # [B, D]
    logp_old: Tensor   # [B, N]
    adv: Tensor        # [B]
    ret: Tensor        # [B] normalized returns (critic targets)
    active: Tensor     # [B, N] bool: robot-controlled carrier blocks
    # log pi_theta_start(a_prop) [B, N] at the update's start parameters: the mechanism
    # diagnostics' reference. None: the current parameters are the start (the update's
    # first minibatch, or a caller outside ``update``), so the reference is the forward itself
    logp_start: Tensor | None = None
    # ``proposal.density_terms(a_robot)`` [B, D] each, computed once per batch (None: at each use)
    u_robot: Tensor | None = None
    log_jac_robot: Tensor | None = None
    # ``sail.sail_rows_np``'s rows (Cn [B, M, D], cn [B, M], keep [B, M]), prepared once per
    # batch by the SAIL methods (None: at each solve)
    sail_Cn: Tensor | None = None
    sail_cn: Tensor | None = None
    sail_keep: Tensor | None = None
    # the actors' proposal center a_bar [B, D] where the batch has it: where the learner's SAIL
    # solves start their Newton loop (None: at a_ST; dropped by the methods that solve none)
    a_bar: Tensor | None = None

    @property
    def a_robot(self) -> Tensor:
        """a_prop with human blocks at 0. A human block holds the human's measured action,
        which may sit on the box face (|a| = 1, outside the proposal's support): it has no
        density and no ratio, so it is never passed to the density as an action."""
        return torch.where(self.fixed, torch.zeros_like(self.a_prop), self.a_prop)

    @property
    def density_terms(self) -> tuple[Tensor, Tensor] | None:
        """What ``proposal_log_prob`` takes from a_robot alone, if stored."""
        return None if self.u_robot is None else (self.u_robot, self.log_jac_robot)

    @property
    def sail_rows(self) -> tuple[Tensor, Tensor, Tensor] | None:
        return None if self.sail_Cn is None else (self.sail_Cn, self.sail_cn, self.sail_keep)

    def with_sail_rows(self, config) -> "Minibatch":
        """With SAIL's prepared rows (``config`` a ``SailConfig``)."""
        rows = sail_rows_np(self.C.numpy(), self.c.numpy(), self.row_mask.numpy(), self.fixed.numpy(),
                            self.a_prop.numpy(), config)
        Cn, cn, keep = (torch.from_numpy(r) for r in rows)
        return dataclasses.replace(self, sail_Cn=Cn, sail_cn=cn, sail_keep=keep)

    def with_density_terms(self) -> "Minibatch":
        u, log_jac = density_terms(self.a_robot)
        return dataclasses.replace(self, u_robot=u, log_jac_robot=log_jac)

    def index(self, idx: Tensor) -> "Minibatch":
        """The rows ``idx`` (a 1-D index tensor) of every field; index_select is
        the same gather as ``v[idx]`` at a third of its cost for the row blocks."""
        return Minibatch(**{k: None if v is None else v.index_select(0, idx) for k, v in self.__dict__.items()})


def check_batch(batch: dict[str, np.ndarray], n_agents: int, obs_dim: int, needs_state: bool) -> dict[str, int]:
    """Keys, shapes (the chunk schema's) and finiteness; a ``ValueError`` naming the
    first bad field. Returns the dims ``T``, ``K``, ``O``, ``M``."""
    missing = [k for k in REQUIRED if k not in batch]
    for k in ("last_obs",) + (("state", "last_state") if needs_state else ()):
        if k not in batch:
            missing.append(k)
    if missing:
        raise ValueError(f"batch is missing {missing}")
    T, K = np.shape(batch["reward"])[:2] if np.ndim(batch["reward"]) == 2 else (None, None)
    if T is None:
        raise ValueError(f"batch['reward'] must be [T,K], got {np.shape(batch['reward'])}")
    M = np.shape(batch["C"])[2] if np.ndim(batch["C"]) == 4 else -1
    dims = {"T": T, "K": K, "O": obs_dim, "M": M}
    for key in REQUIRED:
        want = tuple(dims.get(a, a) for a in SCHEMAS["traj"][key].shape)
        if np.shape(batch[key]) != want:
            raise ValueError(f"batch[{key!r}] has shape {np.shape(batch[key])}, expected {want}")
    if np.shape(batch["last_obs"]) != (K, n_agents, obs_dim):
        raise ValueError(f"batch['last_obs'] has shape {np.shape(batch['last_obs'])}, "
                         f"expected {(K, n_agents, obs_dim)}")
    if "a_bar" in batch and np.shape(batch["a_bar"]) != np.shape(batch["a_prop"]):
        raise ValueError(f"batch['a_bar'] has shape {np.shape(batch['a_bar'])}, expected {np.shape(batch['a_prop'])}")
    for key in ("obs", "a_prop", "logp", "reward", "C", "c") + (("a_bar",) if "a_bar" in batch else ()):
        if not np.all(np.isfinite(batch[key])):
            raise ValueError(f"batch[{key!r}] contains NaN/Inf")
    return dims


def prepare_batch(batch: dict[str, np.ndarray], critic: TeamCritic, value_norm: ValueNormalizer,
                  cfg: AlgoConfig, n_agents: int, obs_dim: int) -> tuple[Minibatch, dict[str, float]]:
    """The checked batch as one flat ``Minibatch`` (advantages normalized, returns in
    the critic's normalized scale) and its ``batch_diagnostics``. Updates ``value_norm``
    with the batch's returns."""
    use_state = critic.state_dim > 0
    dims = check_batch(batch, n_agents, obs_dim, needs_state=use_state)
    T, K = dims["T"], dims["K"]
    f32, f64 = torch.float32, torch.float64
    obs = torch.as_tensor(np.asarray(batch["obs"]), dtype=f32)
    state = torch.as_tensor(np.asarray(batch["state"]), dtype=f32) if use_state \
        else torch.zeros(T, K, 0)
    terminated = np.asarray(batch["terminated"], dtype=bool)
    truncated = np.asarray(batch["truncated"], dtype=bool) & ~terminated

    # values of the visited, last and pre-reset states (normalized -> returns scale)
    with torch.no_grad():
        def values(o: Tensor, s: Tensor) -> np.ndarray:
            v = critic.values(o.reshape(-1, n_agents, obs_dim), s.reshape(-1, s.shape[-1]) if use_state else None)
            return value_norm.denormalize(v).double().numpy()

        value = values(obs, state).reshape(T, K)
        last_state = torch.as_tensor(np.asarray(batch["last_state"]), dtype=f32) if use_state \
            else torch.zeros(K, 0)
        last_value = values(torch.as_tensor(np.asarray(batch["last_obs"]), dtype=f32), last_state)
        final_value = np.zeros((T, K))
        if truncated.any():
            if "final_obs" not in batch:
                raise ValueError("batch has truncated steps but no 'final_obs' [T,K,N,obs_dim]: "
                                 "the critic needs the pre-reset observation to bootstrap")
            fo = torch.as_tensor(np.asarray(batch["final_obs"])[truncated], dtype=f32)
            fs = torch.as_tensor(np.asarray(batch["final_state"])[truncated], dtype=f32) \
                if use_state else None
            final_value[truncated] = values(fo, fs)
    adv, ret = compute_gae(
        batch["reward"], value, next_values(value, last_value, final_value, truncated),
        terminated, truncated, cfg.gamma, cfg.gae_lambda,
    )
    value_norm.update(torch.as_tensor(ret))
    ret_norm = value_norm.normalize(torch.as_tensor(ret)).float()
    adv_t = torch.as_tensor(adv, dtype=f32)
    if cfg.normalize_advantages and adv_t.numel() > 1:
        adv_t = (adv_t - adv_t.mean()) / (adv_t.std() + 1e-8)

    B = T * K
    fixed = torch.as_tensor(np.asarray(batch["fixed_mask"]), dtype=torch.bool).reshape(B, -1)
    data = Minibatch(
        obs=obs.reshape(B, n_agents, obs_dim),
        state=state.reshape(B, state.shape[-1]),
        C=torch.as_tensor(np.asarray(batch["C"]), dtype=f64).reshape(B, dims["M"], -1),
        c=torch.as_tensor(np.asarray(batch["c"]), dtype=f64).reshape(B, dims["M"]),
        row_mask=torch.as_tensor(np.asarray(batch["row_mask"]), dtype=torch.bool).reshape(B, -1),
        fixed=fixed,
        a_prop=torch.as_tensor(np.asarray(batch["a_prop"]), dtype=f64).reshape(B, -1),
        logp_old=torch.as_tensor(np.asarray(batch["logp"]), dtype=f64).reshape(B, -1),
        adv=adv_t.reshape(B),
        ret=ret_norm.reshape(B),
        active=~fixed.view(B, n_agents, CARRIER_ACT_DIM).any(-1),
        a_bar=torch.as_tensor(np.asarray(batch["a_bar"]), dtype=f64).reshape(B, -1) if "a_bar" in batch else None,
    ).with_density_terms()
    return data, batch_diagnostics(batch, adv, ret)


def batch_diagnostics(batch, adv: np.ndarray, ret: np.ndarray) -> dict[str, float]:
    """Whole-batch action diagnostics (numpy, no QP):

    - ``proposal_violation_rate``: share of steps whose raw nominal action a_ST
      violates some live row by more than 1e-6 (as ``evaluate_policy`` counts it);
      per row kind (``proposal_violation_{carrier_wall,payload_wall,formation,any_wall}``)
      only where the batch carries ``row_kind`` ([M] or [T,K,M] ints, 0/1/2 as
      ``common.env.safety``, e.g. ``SafetyConfig.slot_kinds``), for the kinds it has;
      the chunk schema has no such field, so a plain batch gives the "any row" rate only;
    - ``correction_mean`` = mean ||a_exec - a_ST|| (training chain; contains the
      exploration noise a_prop - a_bar), ``exec_minus_prop`` = mean ||a_exec - a_prop||
      (what the shield did to the sampled proposal), ``sail_residual`` = mean
      ||a_bar - a_ST|| (what SAIL moved the center; 0 without SAIL; needs ``a_bar``).
    """
    a_st = np.asarray(batch["a_st"], dtype=np.float64)
    a_exec = np.asarray(batch["a_exec"], dtype=np.float64)
    row_viol = SafetyRows.of(batch).residual(a_st) > VIOLATION_TOL   # as evaluate_policy counts it
    out = {
        "proposal_violation_rate": float(row_viol.any(-1).mean()),
        "correction_mean": float(np.linalg.norm(a_exec - a_st, axis=-1).mean()),
        "exec_minus_prop": float(np.linalg.norm(
            a_exec - np.asarray(batch["a_prop"], dtype=np.float64), axis=-1).mean()),
        "reward_mean": float(np.mean(batch["reward"])),
        "return_mean": float(ret.mean()),
        "adv_std": float(adv.std()),
    }
    if "a_bar" in batch:
        out["sail_residual"] = float(np.linalg.norm(
            np.asarray(batch["a_bar"], dtype=np.float64) - a_st, axis=-1).mean())
    if "row_kind" in batch:
        kind = np.broadcast_to(np.asarray(batch["row_kind"]), row_viol.shape)
        for k, name in enumerate(ROW_KINDS):
            if (kind == k).any():        # kinds the row profile has (no formation under "paper")
                out[f"proposal_violation_{name}"] = float((row_viol & (kind == k)).any(-1).mean())
        out["proposal_violation_any_wall"] = float((row_viol & (kind <= 1)).any(-1).mean())
    return out
