"""The learning methods of Sec. III / IV on hard-tree actors (Table I plus the
``joint_cbf`` ablation).

Which method switches on what (shield, SAIL, joint step, TALO) is ``common.algos.registry``.

The shield itself runs on the actor side; for the learner ``shielded`` only
records that rewards come from ``a_exec``. The likelihood is always the
proposal density at the stored ``a_prop`` (Eq. action_chain).

HAPPO (Kuba et al.; HARL's scheme): a random carrier order (drawn once per
update, as HARL draws it once per training call; ``AlgoConfig.happo_order =
"minibatch"`` redraws it every minibatch); on each minibatch carrier ``i_m``
maximizes ``E[min(r A M, clip(r) A M)]`` where ``M`` is the (detached) product
of the updated ratios of the carriers before it, then ``M`` is multiplied by its
own new ratio. (HARL runs all epochs of one agent before the next; here the
sequence runs within every minibatch.) SAIL+CBF uses this sequential scheme
too (the paper builds SAIL+CBF on the HAPPO baseline); a carrier's center is
computed with its partners' tree outputs detached.

Joint methods (TALO+CBF, SAGE, and the Joint+CBF ablation) step all carriers
together along one flat direction: ``g_TALO`` (common/algos/talo.py, one HVP per
minibatch on the full actor parameter vector) for TALO, ``g_ind`` for
Joint+CBF. ``AlgoConfig.talo_step`` picks how it is applied ("adam": per-carrier
Adam after global norm clipping, entropy gradient added after the projection;
"direct": ``theta <- theta + talo_eta g`` with the entropy gradient inside
``g_ind`` before the projection, no clipping).

Mechanism metrics are measured the same way for every method: W_gap and
cos(g_ind, g_team) (Eq. talo_gap, no HVP needed) on every minibatch, at the
parameters before that minibatch's step, with the surrogates' ratios taken
against the policy at the *update's start* (``rho_i = pi_theta / pi_theta_start``),
not against the behaviour policy that collected the batch. The PPO surrogates
the methods step along keep the behaviour policy's ratio (that is the
algorithm); only the diagnostics change reference. So the first minibatch is at
ratio 1 for every method whatever the policy lag, W_gap is exactly 0 there
without SAIL's coupling (identity center: g_team = g_ind), and its growth over
the update's epochs is what TALO regulates. Summaries per update: ``*_first``,
``*_median``, ``w_gap_geomean`` (exp of the mean log over the minibatches after
the first: the heavy-tailed W_gap's log-mean, in W's units), ``*_mean``, and
every minibatch's value (``w_gap_mb{m}``, ``cos_ind_team_mb{m}``). The
sequential step reuses that measurement's forward (and its SAIL solve).

The local claim of Eq. (talo_condition), measured for every method once per
update (``ab_*``, ``Method.local_ab``): on the update's last minibatch, frozen, at
the parameters before its step, W_gap after a step of equal length along
g_TALO and along g_ind. See docs/interfaces.md for the full list of ``update``
diagnostics.

The centralized critic (common/algos/critic.py) is trained after the actors
on every minibatch, with its own Adam.
"""
from __future__ import annotations

import dataclasses
import json
import math
from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor, nn

from common.algos.adam import Adam
from common.algos.config import AlgoConfig, kappa_schedule, tau_schedule
from common.algos.critic import TeamCritic, ValueNormalizer, compute_gae, next_values
from common.algos.registry import method_spec
from common.algos.talo import (Through, cosine, equal_length_ab, flat_grad, talo_gap, talo_project,
                               unflatten_like)
from common.policy.proposal import proposal_entropy, proposal_log_prob
from common.policy.sail import SailConfig, SailStep, sail_center_implicit, sail_project, sail_step
from common.policy.tree import TreeConfig
from common.policy.tree_torch import TeamPolicy
from common.safety_rows import VIOLATION_TOL, SafetyRows
from common.shield.qp import solve_cbf_qp
from common.spec import CARRIER_ACT_DIM, N_CARRIERS
from common.wire import SCHEMAS

STATE_FORMAT_VERSION = 1
ROW_KINDS = ("carrier_wall", "payload_wall", "formation")   # common.env.safety row kinds 0, 1, 2


# Batch arrays the learner always reads; their shapes are the chunk schema's
# (common/wire.py SCHEMAS["traj"]). "final_obs" is needed only where some step is truncated.
_REQUIRED = ("obs", "C", "c", "row_mask", "fixed_mask", "a_st", "a_prop", "a_exec", "logp",
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

    @property
    def a_robot(self) -> Tensor:
        """a_prop with human blocks at 0. A human block holds the human's measured action,
        which may sit on the box face (|a| = 1, outside the proposal's support): it has no
        density and no ratio, so it is never passed to the density as an action."""
        return torch.where(self.fixed, torch.zeros_like(self.a_prop), self.a_prop)

    def index(self, idx: Tensor) -> "Minibatch":
        """The rows ``idx`` (a 1-D index tensor) of every field; index_select is
        the same gather as ``v[idx]`` at a third of its cost for the row blocks."""
        return Minibatch(**{k: None if v is None else v.index_select(0, idx) for k, v in self.__dict__.items()})


@dataclass
class Surrogates:
    """Eq. (ppo_surrogates) on one forward, with the ratio against one reference policy."""
    log_ratio: Tensor   # [B, N], 0 on human blocks
    L_ind: list[Tensor]   # [L_i], each with the forward's graph
    L_team: Tensor


@dataclass
class StartPoint:
    """What the W_gap diagnostics computed at a minibatch's start parameters, for the
    sequential step to reuse instead of recomputing: the forward (and its SAIL solve)
    and the behaviour-ratio surrogates on its graph (the first carrier's, at M = 1, is
    HAPPO's surrogate for that carrier)."""
    a_st: Tensor        # [B, D] nominal actions (detached)
    step: SailStep | None   # SAIL's implicit step there (None: no implicit SAIL center)
    behaviour: Surrogates
    g_ind: Tensor | None = None   # flat g_ind of ``behaviour`` where the diagnostics took it


class Method:
    """One learner: hard-tree team policy, centralized critic and optimizers."""

    def __init__(self, name: str, cfg: AlgoConfig, obs_dim: int, state_dim: int,
                 n_agents: int = N_CARRIERS):
        spec = method_spec(name)
        if obs_dim < 1 or state_dim < 0:
            raise ValueError(f"bad dims obs_dim={obs_dim}, state_dim={state_dim}")
        self.name, self.cfg = name, cfg
        self.obs_dim, self.state_dim, self.n_agents = int(obs_dim), int(state_dim), n_agents
        self.shielded, self.uses_sail, self.uses_talo = spec.shielded, spec.uses_sail, spec.uses_talo
        self.joint_step = spec.joint_step
        with torch.random.fork_rng():
            torch.manual_seed(cfg.seed)
            self.policy = TeamPolicy(
                n_agents, obs_dim,
                config=TreeConfig(depth=cfg.tree_depth, init_log_std=cfg.init_log_std,
                                  split_k=cfg.split_k, leaf_k=cfg.leaf_k),
            )
            self.critic = TeamCritic(
                n_agents, obs_dim, state_dim if cfg.critic_uses_state else 0,
                hidden=cfg.critic_hidden, latent=cfg.encoder_latent,
            )
        self.value_norm = ValueNormalizer()
        self.trees = list(self.policy.trees)
        self.groups = [list(t.parameters()) for t in self.trees]
        self.group_sizes = [sum(p.numel() for p in g) for g in self.groups]
        self.actor_params = [p for g in self.groups for p in g]
        # one Adam per carrier (HARL style; TALO steps all of them together)
        self.actor_opts = [Adam(g, lr=cfg.actor_lr, eps=1e-5) for g in self.groups]
        self.critic_opt = Adam(self.critic.parameters(), lr=cfg.critic_lr, eps=1e-5)
        # the learner's SAIL forward must equal the actors' (common/policy/rollout.py defaults)
        self.sail_config = SailConfig()
        self.gen = torch.Generator().manual_seed(cfg.seed + 1)
        self.updates = 0
        self.last_happo_factors: dict[int, Tensor] = {}   # carrier -> M used (for tests)
        self.last_happo_orders: list[list[int]] = []      # carrier order of each minibatch of the last update

    # ------------------------------------------------------------------ public API

    def actor_settings(self, progress: float) -> dict[str, float]:
        """Schedules shared with the actors. ``kappa = 0`` means the identity
        center (Pi_0 is the identity), used by the methods without SAIL."""
        return {
            "kappa": kappa_schedule(self.cfg, progress) if self.uses_sail else 0.0,
            "tau": tau_schedule(self.cfg, progress),
        }

    def policy_params(self) -> dict[str, np.ndarray]:
        return self.policy.export_params()

    def update(self, batch: dict[str, np.ndarray], progress: float) -> dict[str, float]:
        """One learner update on a rollout batch (see docs/interfaces.md)."""
        settings = self.actor_settings(progress)
        tau, kappa = settings["tau"], settings["kappa"]
        data, batch_diag = self._prepare(batch)
        batch_diag.update(self._qp_diagnostics(batch))
        B = data.obs.shape[0]
        n_mb = min(self.cfg.minibatches, B)
        sums: dict[str, float] = {}
        counts: dict[str, int] = {}

        def log(stats: dict[str, float]) -> None:
            for k, v in stats.items():
                sums[k] = sums.get(k, 0.0) + float(v)
                counts[k] = counts.get(k, 0) + 1

        # the diagnostics' reference: the policy at the update's start, on every sample
        data.logp_start = self._start_log_prob(data, tau, kappa)
        batch_diag["logratio_at_start"] = self._logratio_at_start(data)
        order: list[int] | None = None
        self.last_happo_orders = []
        w_trace, cos_trace = [], []
        ab = self.cfg.mech_ab_every > 0 and self.updates % self.cfg.mech_ab_every == 0
        for epoch in range(self.cfg.epochs):
            perm = torch.randperm(B, generator=self.gen)
            for j, idx in enumerate(torch.tensor_split(perm, n_mb)):
                mb = data.index(idx)
                if epoch == 0 and j == 0:
                    # at the start parameters: the forward is its own reference (ratio exactly 1,
                    # not 1 +- the rounding of a differently shaped batch's forward)
                    mb.logp_start = None
                before = self._actor_values()
                if self.joint_step:
                    stats, gap = self._joint_step(mb, tau, kappa)
                else:
                    # drawn after epoch 0's permutation, so that every method sees the same minibatches
                    if order is None or self.cfg.happo_order == "minibatch":
                        order = torch.randperm(self.n_agents, generator=self.gen).tolist()
                    gap, start = self._gap_diagnostics(mb, tau, kappa)
                    stats = self._happo_step(mb, tau, kappa, order=order, start=start)
                    self.last_happo_orders.append(list(order))
                step_norm = float(torch.cat([(p.detach() - b).double().reshape(-1)
                                             for p, b in zip(self.actor_params, before)]).norm())
                stats["actor_step_norm"] = step_norm
                # W_gap, cos(g_ind, g_team): measured at the parameters before this minibatch's step
                w_trace.append(gap["w_gap"])
                cos_trace.append(gap["cos_ind_team"])
                if ab and epoch == self.cfg.epochs - 1 and j == n_mb - 1:
                    length = self.cfg.mech_ab_step or step_norm
                    log(self.local_ab(mb, tau, kappa, length, at=before))
                log(stats)
                log(self._critic_step(mb))
        self.updates += 1
        diag = {k: sums[k] / counts[k] for k in sums}
        diag.update(gap_summary(w_trace, cos_trace))
        diag.update(batch_diag)
        diag.update(tau=tau, kappa=kappa, updates=float(self.updates))
        return diag

    def _actor_values(self) -> list[Tensor]:
        return [p.detach().clone() for p in self.actor_params]

    def _set_actor_values(self, values: list[Tensor]) -> None:
        with torch.no_grad():
            for p, v in zip(self.actor_params, values):
                p.copy_(v)

    def _start_log_prob(self, data: Minibatch, tau: float, kappa: float) -> Tensor:
        """log pi_theta(a_prop) [B, N] at the current parameters, without a graph: the
        snapshot of the update's start policy that the diagnostics' ratios divide by."""
        with torch.no_grad():
            a_st = self._tree_actions(data, tau, grad=False)
            center = self._center(data, a_st, kappa, step=self._sail_step(data, a_st, kappa))
            return proposal_log_prob(center, self._log_std(), data.a_robot).detach()

    @staticmethod
    def _logratio_at_start(data: Minibatch) -> float:
        """Mean |log pi_theta_start - log pi_behaviour| over the robot blocks: what the
        policy lag (and actor/learner rounding) put between the two references."""
        if not bool(data.active.any()):
            return 0.0
        return float((data.logp_start - data.logp_old)[data.active].abs().mean())

    # ------------------------------------------------------------------ batch preparation

    def _prepare(self, batch: dict[str, np.ndarray]) -> tuple[Minibatch, dict[str, float]]:
        dims = self._check_batch(batch)
        T, K = dims["T"], dims["K"]
        f32, f64 = torch.float32, torch.float64
        obs = torch.as_tensor(np.asarray(batch["obs"]), dtype=f32)
        use_state = self.critic.state_dim > 0
        state = torch.as_tensor(np.asarray(batch["state"]), dtype=f32) if use_state \
            else torch.zeros(T, K, 0)
        terminated = np.asarray(batch["terminated"], dtype=bool)
        truncated = np.asarray(batch["truncated"], dtype=bool) & ~terminated

        # values of the visited, last and pre-reset states (normalized -> returns scale)
        with torch.no_grad():
            def values(o: Tensor, s: Tensor) -> np.ndarray:
                v = self.critic(o.reshape(-1, self.n_agents, self.obs_dim),
                                s.reshape(-1, s.shape[-1]) if use_state else None)
                return self.value_norm.denormalize(v).double().numpy()

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
            terminated, truncated, self.cfg.gamma, self.cfg.gae_lambda,
        )
        self.value_norm.update(torch.as_tensor(ret))
        ret_norm = self.value_norm.normalize(torch.as_tensor(ret)).float()
        adv_t = torch.as_tensor(adv, dtype=f32)
        if self.cfg.normalize_advantages and adv_t.numel() > 1:
            adv_t = (adv_t - adv_t.mean()) / (adv_t.std() + 1e-8)

        B = T * K
        fixed = torch.as_tensor(np.asarray(batch["fixed_mask"]), dtype=torch.bool).reshape(B, -1)
        data = Minibatch(
            obs=obs.reshape(B, self.n_agents, self.obs_dim),
            state=state.reshape(B, state.shape[-1]),
            C=torch.as_tensor(np.asarray(batch["C"]), dtype=f64).reshape(B, dims["M"], -1),
            c=torch.as_tensor(np.asarray(batch["c"]), dtype=f64).reshape(B, dims["M"]),
            row_mask=torch.as_tensor(np.asarray(batch["row_mask"]), dtype=torch.bool).reshape(B, -1),
            fixed=fixed,
            a_prop=torch.as_tensor(np.asarray(batch["a_prop"]), dtype=f64).reshape(B, -1),
            logp_old=torch.as_tensor(np.asarray(batch["logp"]), dtype=f64).reshape(B, -1),
            adv=adv_t.reshape(B),
            ret=ret_norm.reshape(B),
            active=~fixed.view(B, self.n_agents, CARRIER_ACT_DIM).any(-1),
        )
        return data, self._batch_diagnostics(batch, adv, ret)

    def _check_batch(self, batch: dict[str, np.ndarray]) -> dict[str, int]:
        missing = [k for k in _REQUIRED if k not in batch]
        for k in ("last_obs",) + (("state", "last_state") if self.critic.state_dim else ()):
            if k not in batch:
                missing.append(k)
        if missing:
            raise ValueError(f"batch is missing {missing}")
        T, K = np.shape(batch["reward"])[:2] if np.ndim(batch["reward"]) == 2 else (None, None)
        if T is None:
            raise ValueError(f"batch['reward'] must be [T,K], got {np.shape(batch['reward'])}")
        M = np.shape(batch["C"])[2] if np.ndim(batch["C"]) == 4 else -1
        dims = {"T": T, "K": K, "O": self.obs_dim, "M": M}
        for key in _REQUIRED:
            want = tuple(dims.get(a, a) for a in SCHEMAS["traj"][key].shape)
            if np.shape(batch[key]) != want:
                raise ValueError(f"batch[{key!r}] has shape {np.shape(batch[key])}, expected {want}")
        if np.shape(batch["last_obs"]) != (K, self.n_agents, self.obs_dim):
            raise ValueError(f"batch['last_obs'] has shape {np.shape(batch['last_obs'])}, "
                             f"expected {(K, self.n_agents, self.obs_dim)}")
        for key in ("obs", "a_prop", "logp", "reward", "C", "c"):
            if not np.all(np.isfinite(batch[key])):
                raise ValueError(f"batch[{key!r}] contains NaN/Inf")
        return dims

    @staticmethod
    def _batch_diagnostics(batch, adv: np.ndarray, ret: np.ndarray) -> dict[str, float]:
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

    def _qp_diagnostics(self, batch) -> dict[str, float]:
        """``correction_st``: mean ||Q_CBF(a_ST) - a_ST|| (the deployment correction,
        Eq. qpshield applied to the raw tree action) and ``intervention_rate_st``
        (share with correction > 1e-6), on ``cfg.diag_qp_samples`` evenly spaced
        samples of the batch. Computed for every method; for unshielded HAPPO it is
        a probe only (its deployment runs no QP)."""
        n = int(self.cfg.diag_qp_samples)
        if n <= 0:
            return {}
        T, K = np.shape(batch["reward"])
        B = T * K
        idx = np.unique(np.linspace(0, B - 1, min(n, B)).round().astype(np.int64))

        def rows(key):
            a = np.asarray(batch[key])
            return a.reshape(B, *a.shape[2:])[idx]

        res = solve_cbf_qp(rows("a_st").astype(np.float64), rows("C").astype(np.float64), rows("c").astype(np.float64),
                           rows("row_mask").astype(bool), rows("fixed_mask").astype(bool))
        return {"correction_st": float(res.correction_norm.mean()),
                "intervention_rate_st": float((res.correction_norm > 1e-6).mean())}

    # ------------------------------------------------------------------ policy pieces

    def _log_std(self) -> Tensor:
        return torch.cat([t.log_std for t in self.trees])

    def _tree_actions(self, mb: Minibatch, tau: float, grad: bool) -> Tensor:
        """Stacked ST nominal actions a_ST [B, D], all trees in one batched forward;
        ``grad=False``: without a graph."""
        with torch.set_grad_enabled(grad):
            return self.policy(mb.obs, tau).action

    def _through(self, a_st: Tensor) -> Through:
        """The route of ``talo_gap``'s coupled blocks: tree i reaches the surrogates only
        through its block of a_ST, its log_std directly."""
        return Through(a_st, [slice(CARRIER_ACT_DIM * i, CARRIER_ACT_DIM * (i + 1)) for i in range(self.n_agents)],
                       [[t.W, t.b, t.K, t.beta] for t in self.trees])

    def _sail_step(self, mb: Minibatch, a_st: Tensor, kappa: float) -> SailStep | None:
        """SAIL's solve and implicit step at ``a_st`` (None where the center is not
        the implicit SAIL map), for ``_center`` to build graphs on."""
        if not self.uses_sail or self.cfg.sail_grad == "unrolled":
            return None
        return sail_step(a_st, mb.C, mb.c, mb.row_mask, kappa, mb.fixed, mb.a_prop, self.sail_config)

    def _center(self, mb: Minibatch, a_st: Tensor, kappa: float,
                step: SailStep | None = None) -> Tensor:
        """Proposal center: SAIL map Pi_kappa(x, a_ST) (Eq. sail_projection) or identity.
        Human blocks sit at their measured action (= stored a_prop there). ``step``:
        ``_sail_step``'s answer at the same values of a_ST, if already computed."""
        if not self.uses_sail:
            return torch.where(mb.fixed, mb.a_prop.to(a_st.dtype), a_st)
        if self.cfg.sail_grad == "unrolled":
            return sail_project(a_st.double(), mb.C, mb.c, mb.row_mask, kappa,
                                fixed_mask=mb.fixed, fixed_action=mb.a_prop, config=self.sail_config)
        return sail_center_implicit(a_st, mb.C, mb.c, mb.row_mask, kappa, mb.fixed, mb.a_prop,
                                    self.sail_config, step=step)

    def _log_ratio(self, mb: Minibatch, center: Tensor, log_std: Tensor) -> Tensor:
        """Per-carrier log-likelihood ratio against the behaviour policy at the stored
        a_prop [B, N]; 0 on human blocks (``_ratio_against``)."""
        return self._ratio_against(mb, proposal_log_prob(center, log_std, mb.a_robot), mb.logp_old)

    @staticmethod
    def _ratio_against(mb: Minibatch, logp: Tensor, reference: Tensor) -> Tensor:
        return torch.where(mb.active, logp - reference, torch.zeros_like(logp))

    def _clipped(self, ratio: Tensor, adv: Tensor) -> Tensor:
        """l(rho, A) = min(rho A, clip(rho, 1-eps, 1+eps) A) (Eq. ppo_surrogates)."""
        eps = self.cfg.clip
        return torch.minimum(ratio * adv, ratio.clamp(1 - eps, 1 + eps) * adv)

    def _surrogates(self, mb: Minibatch, log_ratio: Tensor) -> tuple[list[Tensor], Tensor]:
        """Eq. (ppo_surrogates): L_i and L_team (team ratio = product over robot carriers)."""
        adv = mb.adv[:, None]
        per = self._clipped(log_ratio.exp(), adv) * mb.active
        L_ind = list(per.mean(0).unbind(0))
        L_team = self._clipped(log_ratio.sum(1).exp(), mb.adv).mean()
        return L_ind, L_team

    def _ratio_stats(self, log_ratio: Tensor, active: Tensor) -> dict[str, float]:
        with torch.no_grad():
            n = active.sum().clamp(min=1)
            ratio = log_ratio.exp()
            kl = ((ratio - 1) - log_ratio)[active].sum() / n
            clipped = ((ratio - 1).abs() > self.cfg.clip)[active].sum() / n
        return {"approx_kl": float(kl), "clip_frac": float(clipped)}

    def _entropy(self) -> Tensor:
        return proposal_entropy(self._log_std())   # [N]

    # ------------------------------------------------------------------ actor updates

    def _start_point(self, mb: Minibatch, tau: float, kappa: float):
        """One forward at the current parameters (all carriers attached) and the
        surrogates on it twice: ``behaviour`` (ratio against the behaviour policy: the
        PPO surrogates the methods step along) and ``start`` (ratio against the update's
        start policy ``mb.logp_start``: the mechanism diagnostics).
        Where the two references agree bitwise on the minibatch (on-policy data: the
        actors' log-density is the learner's), ``start is behaviour``, and whatever is
        computed on one serves the other. Returns (a_ST, SAIL step or None, behaviour, start)."""
        a_st = self._tree_actions(mb, tau, grad=True)
        step = self._sail_step(mb, a_st, kappa)
        logp = proposal_log_prob(self._center(mb, a_st, kappa, step=step), self._log_std(), mb.a_robot)
        behaviour = self._surrogates_against(mb, logp, mb.logp_old)
        reference = logp.detach() if mb.logp_start is None else mb.logp_start
        start_ratio = self._ratio_against(mb, logp, reference)
        if torch.equal(start_ratio, behaviour.log_ratio):
            return a_st, step, behaviour, behaviour
        return a_st, step, behaviour, self._surrogates_against(mb, logp, reference)

    def _surrogates_against(self, mb: Minibatch, logp: Tensor, reference: Tensor) -> Surrogates:
        log_ratio = self._ratio_against(mb, logp, reference)
        return Surrogates(log_ratio, *self._surrogates(mb, log_ratio))

    def _gap(self, a_st: Tensor, s: Surrogates, with_hvp: bool):
        """Eq. (talo_gap) on surrogates ``s`` built on the forward that produced ``a_st``."""
        return talo_gap(s.L_ind, s.L_team, self.groups, separable=not self.uses_sail,
                        with_hvp=with_hvp, through=self._through(a_st))

    @staticmethod
    def _gap_stats(g_ind: Tensor, g_team: Tensor, w_gap) -> dict[str, float]:
        return {"w_gap": float(w_gap), "cos_ind_team": cosine(g_ind, g_team)}

    def _gap_diagnostics(self, mb: Minibatch, tau: float, kappa: float):
        """W_gap and cos(g_ind, g_team) (Eq. talo_gap, no HVP, ratios against the update's
        start) at the current parameters, for the sequential methods (the joint step
        measures them itself). Also returns the ``StartPoint``, which the HAPPO step
        reuses: the forward (saves a SAIL solve) and its first carrier's surrogate."""
        a_st, step, behaviour, start = self._start_point(mb, tau, kappa)
        g_ind, g_team, w, _ = self._gap(a_st, start, with_hvp=False)
        return self._gap_stats(g_ind, g_team, w), \
            StartPoint(a_st.detach().clone(), step, behaviour, g_ind if start is behaviour else None)

    def local_ab(self, mb: Minibatch, tau: float, kappa: float, length: float,
                 at: list[Tensor] | None = None) -> dict[str, float]:
        """The local claim of Eq. (talo_condition) as a measurement, the same for every
        method: on the frozen minibatch ``mb`` at parameters ``at`` (default: the
        current ones), W_gap (ratios against the update's start, as the diagnostics)
        after a step of length ``length`` along g_TALO (Eq. talo_projection, this
        config's sigma and eps) and along g_ind. Leaves the parameters as it found them.

        ``ab_w_before``, ``ab_w_talo``, ``ab_w_ind``, ``ab_ratio`` = ab_w_talo / ab_w_ind
        (< 1: TALO's direction kept the gap smaller; NaN where ab_w_ind = 0),
        ``ab_rate_talo``, ``ab_rate_ind`` (the first-order rates grad W . g / ||g|| of the
        two directions, what Eq. talo_condition is about; in the split parameters' blocks
        grad W is the straight-through surrogate, common/algos/talo.py),
        ``ab_corrected`` (Delta_gap > 0; else g_TALO = g_ind and the ratio is 1) and
        ``ab_step`` (the length)."""
        current = self._actor_values()
        try:
            if at is not None:
                self._set_actor_values(at)
            base = self._actor_values()
            if mb.logp_start is None:   # these parameters are the start: fix the reference here
                mb = dataclasses.replace(mb, logp_start=self._start_log_prob(mb, tau, kappa))
            a_st, _, _, start = self._start_point(mb, tau, kappa)
            g_ind, _, w0, grad_w = self._gap(a_st, start, with_hvp=True)
            g_talo, delta = talo_project(g_ind, grad_w, w0, self.cfg.talo_sigma, self.cfg.talo_eps)

            def w_at(displacement: Tensor) -> float:
                self._set_actor_values([b + d.to(b.dtype) for b, d in
                                        zip(base, unflatten_like(displacement, self.actor_params))])
                a_st, _, _, start = self._start_point(mb, tau, kappa)
                return float(self._gap(a_st, start, with_hvp=False)[2])

            w_talo, w_ind = equal_length_ab(w_at, float(w0), g_talo, g_ind, length)
        finally:
            self._set_actor_values(current)
        def rate(g: Tensor) -> float:
            n = float(g.norm())
            return float(grad_w @ g) / n if n > 0 else 0.0

        return {"ab_w_before": float(w0), "ab_w_talo": w_talo, "ab_w_ind": w_ind,
                "ab_ratio": w_talo / w_ind if w_ind > 0 else math.nan,
                "ab_rate_talo": rate(g_talo), "ab_rate_ind": rate(g_ind),
                "ab_corrected": float(delta > 0.0), "ab_step": float(length)}

    def _joint_step(self, mb: Minibatch, tau: float, kappa: float) -> tuple[dict[str, float], dict]:
        """All carriers stepped together: along g_TALO (Eqs. talo_gap .. talo_projection)
        for TALO methods, along g_ind for Joint+CBF; applied per ``cfg.talo_step``.
        Returns (stats, gap stats measured before the step)."""
        cfg = self.cfg
        a_st, _, behaviour, start = self._start_point(mb, tau, kappa)
        log_ratio, L_ind, L_team = behaviour.log_ratio, behaviour.L_ind, behaviour.L_team
        # the algorithm's gap: ratios against the behaviour policy (Eq. ppo_surrogates)
        g_ind, g_team, w, grad_w = self._gap(a_st, behaviour, with_hvp=self.uses_talo)
        # the diagnostics' gap: ratios against the update's start (the same one on-policy)
        gap = self._gap_stats(g_ind, g_team, w) if start is behaviour \
            else self._gap_stats(*self._gap(a_st, start, with_hvp=False)[:3])
        entropy = self._entropy()
        g_ent = cfg.ent_coef * flat_grad(entropy.sum(), self.actor_params) if cfg.ent_coef > 0 \
            else torch.zeros_like(g_ind)
        direct = cfg.talo_step == "direct"
        stats = self._ratio_stats(log_ratio, mb.active)
        if self.uses_talo:
            # direct: entropy inside g_ind, so the step taken is the projected one;
            # adam: entropy after the projection (only touches log_std)
            g, delta = talo_project(g_ind + g_ent if direct else g_ind, grad_w, w,
                                    cfg.talo_sigma, cfg.talo_eps)
            if not direct:
                g = g + g_ent
            stats.update(delta_gap=delta, talo_corrected=float(delta > 0.0))
        else:
            g = g_ind + g_ent
        before = [p.detach().clone() for p in self.actor_params] if self.uses_talo else None
        if direct:
            with torch.no_grad():
                for p, d in zip(self.actor_params, unflatten_like(g, self.actor_params)):
                    p.add_(d.to(p.dtype), alpha=cfg.talo_eta)
            grad_norm = float(g.norm())
        else:
            for p, d in zip(self.actor_params, unflatten_like(g, self.actor_params)):
                p.grad = -d.detach().clone()      # ascent on surrogates -> descent for Adam
            grad_norm = float(nn.utils.clip_grad_norm_(self.actor_params, cfg.max_grad_norm))
            for opt in self.actor_opts:
                opt.step()
        if self.uses_talo:
            met, decreases, floor = self._talo_condition(grad_w, w, g_ind, g_team, before, direct)
            stats.update(talo_condition_met=met, talo_step_decreases_gap=decreases,
                         talo_gap_at_floor=floor)
        stats.update(
            policy_loss=-float(sum(L_ind).detach()), team_loss=-float(L_team.detach()),
            entropy=float(entropy.detach().mean()), actor_grad_norm=grad_norm,
        )
        return stats, gap

    def _talo_condition(self, grad_w: Tensor, w_gap, g_ind: Tensor, g_team: Tensor,
                        before: list[Tensor], direct: bool) -> tuple[float, float, float]:
        """Does the step actually applied, delta = theta_after - theta_before, meet
        Eq. (talo_condition) to first order, grad W . delta <= -sigma W_gap eta?

        eta is ``talo_eta`` for the direct step and ``actor_lr`` (Adam's nominal step
        size) for the adam step. Tolerance: 1e-6 relative plus the rounding of the
        parameters themselves (float32 parameters cannot represent delta exactly).
        Where W_gap is at the rounding floor of the gradients it is built from
        (W <= (8 eps (||g_ind|| + ||g_team||))^2 / 2, i.e. g_ind = g_team to working
        precision: the first minibatch of an identity-center method, where the ratios
        are 1 and the two gradients agree analytically) both sides are rounding noise
        and ||grad W||^2 << talo_eps switches the correction off; the condition is
        then counted as met (vacuous) and reported in ``talo_gap_at_floor``.
        Returns (met, grad W . delta < 0, at_floor) as 0/1."""
        eta = self.cfg.talo_eta if direct else self.cfg.actor_lr
        gw = grad_w.detach().double()
        after = torch.cat([p.detach().reshape(-1) for p in self.actor_params])
        start = torch.cat([b.reshape(-1) for b in before])
        delta = after.double() - start.double()
        lhs = float(gw @ delta)
        rhs = -self.cfg.talo_sigma * float(w_gap) * eta
        eps = torch.finfo(after.dtype).eps
        ulp = eps * torch.maximum(after.abs(), start.abs()).double()
        tol = 1e-6 * (abs(rhs) + float(gw.norm() * delta.norm())) + float(gw.abs() @ ulp)
        floor = 0.5 * (8.0 * torch.finfo(g_ind.dtype).eps * float(g_ind.norm() + g_team.norm())) ** 2
        at_floor = float(w_gap) <= floor
        return float(at_floor or lhs <= rhs + tol), float(lhs < 0.0), float(at_floor)

    def _happo_step(self, mb: Minibatch, tau: float, kappa: float, order: list[int] | None = None,
                    start: StartPoint | None = None) -> dict[str, float]:
        """HAPPO sequential per-carrier clipped updates with the M factor, carriers
        in ``order`` (a fresh random one if None). ``start`` = the diagnostics'
        ``StartPoint`` at the current parameters, if already computed."""
        if order is None:
            order = torch.randperm(self.n_agents, generator=self.gen).tolist()
        factor = torch.ones_like(mb.adv)
        if start is not None:
            a_st_cache, step_cache = start.a_st, start.step
        else:
            with torch.no_grad():      # forward at the current parameters
                a_st_cache = self._tree_actions(mb, tau, grad=False)
                step_cache = self._sail_step(mb, a_st_cache, kappa)
        self.last_happo_factors = {}
        losses, kls, clips, ents, norms = [], [], [], [], []
        for i in order:
            self.last_happo_factors[i] = factor.clone()
            tree = self.trees[i]
            block = slice(CARRIER_ACT_DIM * i, CARRIER_ACT_DIM * (i + 1))
            log_std = torch.cat([t.log_std if j == i else t.log_std.detach()
                                 for j, t in enumerate(self.trees)])
            active = mb.active[:, i]
            self.actor_opts[i].zero_grad()
            if start is not None and i == order[0]:
                # M = 1: this carrier's surrogate is L_i at the start point, on the
                # diagnostics' forward; only the entropy is added
                log_ratio, surr = start.behaviour.log_ratio[:, i].detach(), start.behaviour.L_ind[i]
                g_i = start.g_ind.split(self.group_sizes)[i] if start.g_ind is not None \
                    else flat_grad(surr, self.groups[i])
                grads = unflatten_like(g_i, self.groups[i])
                for p, g in zip(self.groups[i], grads):
                    p.grad = -g                  # ascent on L_i -> descent for Adam
                surr = surr.detach()
            else:
                own = tree(mb.obs[:, i], tau).action
                a_st = torch.cat([a_st_cache[:, :block.start], own, a_st_cache[:, block.stop:]], dim=-1)
                # same values as the cached forward: reuse its SAIL step, build the graph only
                center = self._center(mb, a_st, kappa, step=step_cache)
                log_ratio = self._log_ratio(mb, center, log_std)[:, i]
                surr = (self._clipped(log_ratio.exp(), mb.adv * factor) * active).mean()
            entropy = proposal_entropy(log_std)[i]
            loss = -(surr + self.cfg.ent_coef * entropy)
            loss.backward()                      # adds to a reused gradient
            norms.append(float(nn.utils.clip_grad_norm_(self.groups[i], self.cfg.max_grad_norm)))
            self.actor_opts[i].step()
            stats = self._ratio_stats(log_ratio[:, None], active[:, None])
            losses.append(float(loss.detach())); ents.append(float(entropy.detach()))
            kls.append(stats["approx_kl"]); clips.append(stats["clip_frac"])
            if i == order[-1]:
                break   # no carrier after this one: its M would go unused (saves a SAIL solve)
            # M <- M * rho_i(theta_i new)  (HARL: ratio of the updated carrier, detached)
            with torch.no_grad():
                a_st_cache[:, block] = tree(mb.obs[:, i], tau).action
                step_cache = self._sail_step(mb, a_st_cache, kappa)
                new = self._log_ratio(mb, self._center(mb, a_st_cache, kappa, step=step_cache),
                                      self._log_std())[:, i]
                factor = factor * torch.where(active, new.exp(), torch.ones_like(new))
        return {"policy_loss": float(np.sum(losses)), "approx_kl": float(np.mean(kls)),
                "clip_frac": float(np.mean(clips)), "entropy": float(np.mean(ents)),
                "actor_grad_norm": float(np.mean(norms)),
                # spread of the M factor the last carrier in the order was updated with
                "happo_factor_std": float(factor.std()) if factor.numel() > 1 else 0.0}

    # ------------------------------------------------------------------ critic

    def _critic_step(self, mb: Minibatch) -> dict[str, float]:
        v = self.critic(mb.obs, mb.state if self.critic.state_dim else None)
        loss = self.cfg.vf_coef * (v - mb.ret).pow(2).mean()
        self.critic_opt.zero_grad()
        loss.backward()
        nn.utils.clip_grad_norm_(self.critic.parameters(), self.cfg.max_grad_norm)
        self.critic_opt.step()
        return {"value_loss": float(loss.detach())}

    # ------------------------------------------------------------------ checkpoints

    def state_dict(self) -> dict:
        """Weights-only-safe (tensors, numbers, strings, lists, dicts)."""
        return {
            "format_version": STATE_FORMAT_VERSION,
            "method": self.name,
            "config": json.dumps(self.cfg.to_dict(), sort_keys=True),
            "obs_dim": self.obs_dim,
            "state_dim": self.state_dim,
            "policy": self.policy.state_dict(),
            "critic": self.critic.state_dict(),
            "value_norm": self.value_norm.state_dict(),
            "actor_opts": [o.state_dict() for o in self.actor_opts],
            "critic_opt": self.critic_opt.state_dict(),
            "updates": self.updates,
            "rng": self.gen.get_state(),
        }

    def load_state_dict(self, state: dict) -> None:
        if state.get("format_version") != STATE_FORMAT_VERSION:
            raise ValueError(f"unsupported learner state format {state.get('format_version')!r}")
        if state.get("method") != self.name:
            raise ValueError(f"checkpoint is for method {state.get('method')!r}, not {self.name!r}")
        if (state.get("obs_dim"), state.get("state_dim")) != (self.obs_dim, self.state_dim):
            raise ValueError("checkpoint obs_dim/state_dim do not match this learner")
        self.policy.load_state_dict(state["policy"])
        self.critic.load_state_dict(state["critic"])
        self.value_norm.load_state_dict(state["value_norm"])
        if len(state["actor_opts"]) != len(self.actor_opts):
            raise ValueError("checkpoint has a different number of actor optimizers")
        for opt, s in zip(self.actor_opts, state["actor_opts"]):
            opt.load_state_dict(s)
        self.critic_opt.load_state_dict(state["critic_opt"])
        self.updates = int(state["updates"])
        self.gen.set_state(state["rng"])


def gap_summary(w_gap: list[float], cos: list[float]) -> dict[str, float]:
    """An update's W_gap and cos(g_ind, g_team), one value per minibatch in order, as
    metrics-row entries: each minibatch's value (``w_gap_mb{m}``, ``cos_ind_team_mb{m}``),
    the first (at the update's start, ratio 1), the median, the mean and, for W_gap (heavy
    tailed: one update can be 1e3 times the median), the geometric mean over the
    minibatches after the first, ``exp(mean ln W)`` (0 if one of them is 0; NaN with a
    single minibatch). ``w_gap`` / ``cos_ind_team`` repeat the means (the training curves'
    keys, sage/report.py)."""
    w, c = np.asarray(w_gap, dtype=np.float64), np.asarray(cos, dtype=np.float64)
    out = {f"w_gap_mb{m}": float(v) for m, v in enumerate(w)}
    out.update({f"cos_ind_team_mb{m}": float(v) for m, v in enumerate(c)})
    steps = w[1:]
    with np.errstate(divide="ignore"):
        geomean = float(np.exp(np.log(steps).mean())) if len(steps) else math.nan
    out.update(w_gap_first=float(w[0]), w_gap_median=float(np.median(w)), w_gap_mean=float(w.mean()),
               w_gap_geomean=geomean, w_gap_last=float(w[-1]),
               cos_ind_team_first=float(c[0]), cos_ind_team_median=float(np.median(c)),
               cos_ind_team_mean=float(c.mean()))
    out["w_gap"], out["cos_ind_team"] = out["w_gap_mean"], out["cos_ind_team_mean"]
    return out


def make_method(name: str, cfg: AlgoConfig | None, obs_dim: int, state_dim: int) -> Method:
    """Factory named in docs/interfaces.md."""
    return Method(name, cfg or AlgoConfig(), obs_dim, state_dim)
