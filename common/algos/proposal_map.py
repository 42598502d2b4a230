"""The proposal map as the learner differentiates it: hard-tree ST actions a_ST
(Eq. st_gate), the proposal center (the SAIL map Pi_kappa, Eq. sail_projection,
with its implicit step, Eq. sail_jacobian, or the identity), the proposal
log-density at the stored a_prop and its ratios, and the clipped PPO surrogates
built on them (Eq. ppo_surrogates).

The learner's forward must equal the actors' (common/policy/rollout.py): the same
trees, the same SAIL config, the same center for human blocks (their measured
action, the stored a_prop there; log-ratio 0 on those blocks).
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from common.algos import surrogate_chain
from common.algos.batch import Minibatch
from common.algos.gap_closed_form import TREE_PARAMETERS, Layout, Taped, cotangent_sets, gradient, \
    talo_gap_closed_form
from common.algos.surrogate_chain import clipped, surrogate_values
from common.algos.talo import Through, talo_gap
from common.policy.proposal import proposal_entropy, proposal_log_prob
from common.policy.sail import SailConfig, SailStep, sail_center_implicit, sail_project, sail_step
from common.policy.tree_torch import TeamPolicy
from common.spec import CARRIER_ACT_DIM


@dataclass
class Surrogates:
    """Eq. (ppo_surrogates) on one forward, with the ratio against one reference policy."""
    log_ratio: Tensor   # [B, N], 0 on human blocks
    L_ind: list[Tensor]   # [L_i], each with the forward's graph (none where ``taped``)
    L_team: Tensor
    taped: Taped | None = None   # the forward's tapes, where its derivatives are in closed form
    reference: int = 0           # which of the forward's references these surrogates divide by


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


class ProposalMap:
    """a_ST -> center -> log pi(a_prop) for one team policy; ``uses_sail`` picks the
    SAIL center (``sail_grad``: "implicit" or "unrolled" gradient) over the identity.
    ``closed_form``: TALO's gap from the written-out derivatives (common/algos/
    gap_closed_form.py) where the center allows it (not the unrolled SAIL gradient); False:
    autograd on the graph, the reference the closed form is tested against."""

    def __init__(self, policy: TeamPolicy, uses_sail: bool, sail_grad: str, clip: float,
                 closed_form: bool = True):
        self.policy, self.uses_sail, self.sail_grad, self.clip = policy, uses_sail, sail_grad, clip
        self.trees = list(policy.trees)
        self.groups = [list(t.parameters()) for t in self.trees]   # theta_i, carrier i's parameters
        self.params = [p for g in self.groups for p in g]           # theta, the flat actor vector's order
        self.n_agents = len(self.trees)
        if any(tuple(n for n, _ in t.named_parameters()) != TREE_PARAMETERS for t in self.trees):
            raise ValueError(f"proposal map: each tree's parameters must be {TREE_PARAMETERS}")
        self.closed_form = closed_form and not (uses_sail and sail_grad == "unrolled")
        self.layout = Layout(self.groups)
        # the learner's SAIL forward must equal the actors' (common/policy/rollout.py defaults)
        self.sail_config = SailConfig()

    # ------------------------------------------------------------------ the forward

    def log_std(self) -> Tensor:
        return torch.cat([t.log_std for t in self.trees])

    def entropy(self) -> Tensor:
        return proposal_entropy(self.log_std())   # [N]

    def tree_actions(self, mb: Minibatch, tau: float, grad: bool) -> Tensor:
        """Stacked ST nominal actions a_ST [B, D] (Eq. st_gate), all trees in one
        batched forward; ``grad=False``: without a graph."""
        with torch.set_grad_enabled(grad):
            return self.policy(mb.obs, tau).action

    def through(self, a_st: Tensor) -> Through:
        """The route of ``talo_gap``'s coupled blocks: tree i reaches the surrogates only
        through its block of a_ST, its log_std directly."""
        return Through(a_st, [slice(CARRIER_ACT_DIM * i, CARRIER_ACT_DIM * (i + 1)) for i in range(self.n_agents)],
                       [[t.W, t.b, t.K, t.beta] for t in self.trees])

    def sail_step(self, mb: Minibatch, a_st: Tensor, kappa: float) -> SailStep | None:
        """SAIL's solve and implicit step (Eq. sail_jacobian) at ``a_st`` (None where the
        center is not the implicit SAIL map), for ``center`` to build graphs on."""
        if not self.uses_sail or self.sail_grad == "unrolled":
            return None
        return sail_step(a_st, mb.C, mb.c, mb.row_mask, kappa, mb.fixed, mb.a_prop, self.sail_config,
                         rows=mb.sail_rows, start=mb.a_bar)

    def prepared(self, data: Minibatch) -> Minibatch:
        """``data`` with what every solve of its minibatches reuses where the center is the
        implicit SAIL map: SAIL's prepared rows, and the actors' solutions a_bar as the
        solves' warm start (the policy moves little within an update, so the loop from
        there mostly ends on its first step; the answer is the same to rounding,
        ``sail_implicit_step_np``). Elsewhere without a_bar, which no solve reads."""
        if not self.uses_sail or self.sail_grad == "unrolled":
            return dataclasses.replace(data, a_bar=None)
        return data.with_sail_rows(self.sail_config)

    def center(self, mb: Minibatch, a_st: Tensor, kappa: float, step: SailStep | None = None) -> Tensor:
        """Proposal center: SAIL map Pi_kappa(x, a_ST) (Eq. sail_projection) or identity.
        Human blocks sit at their measured action (= stored a_prop there). ``step``:
        ``sail_step``'s answer at the same values of a_ST, if already computed."""
        if not self.uses_sail:
            return torch.where(mb.fixed, mb.a_prop.to(a_st.dtype), a_st)
        if self.sail_grad == "unrolled":
            return sail_project(a_st.double(), mb.C, mb.c, mb.row_mask, kappa,
                                fixed_mask=mb.fixed, fixed_action=mb.a_prop, config=self.sail_config)
        return sail_center_implicit(a_st, mb.C, mb.c, mb.row_mask, kappa, mb.fixed, mb.a_prop,
                                    self.sail_config, step=step)

    def start_log_prob(self, data: Minibatch, tau: float, kappa: float) -> Tensor:
        """log pi_theta(a_prop) [B, N] at the current parameters, without a graph: the
        snapshot of the update's start policy that the diagnostics' ratios divide by."""
        with torch.no_grad():
            a_st = self.tree_actions(data, tau, grad=False)
            center = self.center(data, a_st, kappa, step=self.sail_step(data, a_st, kappa))
            return proposal_log_prob(center, self.log_std(), data.a_robot, terms=data.density_terms).detach()

    # ------------------------------------------------------------------ ratios and surrogates

    def log_ratio(self, mb: Minibatch, center: Tensor, log_std: Tensor) -> Tensor:
        """Per-carrier log-likelihood ratio against the behaviour policy at the stored
        a_prop [B, N]; 0 on human blocks (their density is never evaluated: ``Minibatch.a_robot``)."""
        return self.ratio_against(mb, proposal_log_prob(center, log_std, mb.a_robot, terms=mb.density_terms),
                                  mb.logp_old)

    @staticmethod
    def ratio_against(mb: Minibatch, logp: Tensor, reference: Tensor) -> Tensor:
        return torch.where(mb.active, logp - reference, torch.zeros_like(logp))

    def clipped(self, ratio: Tensor, adv: Tensor) -> Tensor:
        """l(rho, A) = min(rho A, clip(rho, 1-eps, 1+eps) A) (Eq. ppo_surrogates)."""
        return clipped(ratio, adv, self.clip)

    def surrogates(self, mb: Minibatch, log_ratio: Tensor) -> tuple[list[Tensor], Tensor]:
        """Eq. (ppo_surrogates): L_i and L_team (team ratio = product over robot carriers)."""
        values = surrogate_values(log_ratio, mb.adv, mb.active, self.clip)
        return list(values[:self.n_agents].unbind(0)), values[self.n_agents]

    def ratio_stats(self, log_ratio: Tensor, active: Tensor) -> dict[str, float]:
        with torch.no_grad():
            n = active.sum().clamp(min=1)
            ratio = log_ratio.exp()
            kl = ((ratio - 1) - log_ratio)[active].sum() / n
            outside = ((ratio - 1).abs() > self.clip)[active].sum() / n
        return {"approx_kl": float(kl), "clip_frac": float(outside)}

    def start_point(self, mb: Minibatch, tau: float, kappa: float):
        """One forward at the current parameters (all carriers attached) and the
        surrogates on it twice: ``behaviour`` (ratio against the behaviour policy: the
        PPO surrogates the methods step along) and ``start`` (ratio against the update's
        start policy ``mb.logp_start``, this forward's own where None: the mechanism
        diagnostics). Where the two ratios agree bitwise on the minibatch (on-policy data:
        the actors' log-density is the learner's), ``start is behaviour``, and whatever is
        computed on one serves the other. From a_ST on, the surrogates and their first and
        second derivatives are the closed form of common/algos/surrogate_chain.py; with
        ``closed_form`` the trees' too, and the forward keeps tapes instead of a graph.
        Returns (a_ST, SAIL step or None, behaviour, start)."""
        references = (mb.logp_old, mb.logp_start)
        if self.closed_form:
            forest = self.policy.taped(mb.obs, tau)
            a_st = forest.action
            step = self.sail_step(mb, a_st, kappa)
            values, log_ratios, chain = surrogate_chain.chain_surrogates_taped(
                a_st, self.log_std(), mb, step, references, self.clip)
            taped = Taped(forest, chain)
        else:
            a_st = self.tree_actions(mb, tau, grad=True)
            step = self.sail_step(mb, a_st, kappa)
            values, log_ratios = self.surrogates_at(mb, a_st, self.log_std(), kappa, step, references)
            taped = None
        N = self.n_agents
        behaviour, start = (Surrogates(r, list(v[:N].unbind(0)), v[N], taped, k)
                            for k, (r, v) in enumerate(zip(log_ratios, values)))
        if torch.equal(log_ratios[1], log_ratios[0]):
            return a_st, step, behaviour, behaviour
        return a_st, step, behaviour, start

    def surrogates_at(self, mb: Minibatch, a_st: Tensor, log_std: Tensor, kappa: float, step: SailStep | None,
                      references) -> tuple[Tensor, Tensor]:
        """Surrogates [R, N+1] and log-ratios [R, B, N] at ``a_st`` against ``references``
        (``surrogate_chain.chain_surrogates``; ``step``: the SAIL step at these values of
        a_ST). The unrolled SAIL gradient keeps the autograd graph of ``center``."""
        if self.uses_sail and self.sail_grad == "unrolled":
            logp = proposal_log_prob(self.center(mb, a_st, kappa), log_std, mb.a_robot, terms=mb.density_terms)
            return surrogate_chain.surrogates_of_log_density(logp, references, mb.adv, mb.active, self.clip)
        return surrogate_chain.chain_surrogates(a_st, log_std, mb, step, references, self.clip)

    def carrier_surrogate(self, mb: Minibatch, a_st: Tensor, log_std: Tensor, kappa: float,
                          step: SailStep | None, i: int) -> tuple[Tensor, Tensor]:
        """Carrier ``i``'s log-ratio against the behaviour policy [B] (detached) and its
        surrogate L_i (Eq. ppo_surrogates) at ``a_st`` (the sequential step's per-carrier
        forward)."""
        values, log_ratios = self.surrogates_at(mb, a_st, log_std, kappa, step, (mb.logp_old,))
        return log_ratios[0, :, i].detach(), values[0, i]

    def carrier_gradient(self, mb: Minibatch, a_st: Tensor, kappa: float, step: SailStep | None, i: int,
                         forest) -> tuple[Tensor, Tensor, Tensor]:
        """``carrier_surrogate``'s log-ratio [B] and L_i, and its gradient in theta_i (flat, carrier
        i's W, b, K, beta, log_std) in closed form: the chain at ``a_st`` (partners' blocks
        constant, as there) and tree i's VJP from ``forest``, the tape of a forward at which
        tree i had its current parameters (HAPPO's carriers before their turn: the step's
        start point). No autograd graph."""
        N = self.n_agents
        values, log_ratios, chain = surrogate_chain.chain_surrogates_taped(
            a_st, self.log_std(), mb, step, (mb.logp_old,), self.clip)
        sets = np.zeros((N, 1, N + 1))    # L_i on carrier i's block only (the others' sets empty)
        sets[i, 0, i] = 1.0
        g = gradient(Taped(forest, chain), sets, self.layout)
        per = g.numel() // N
        return log_ratios[0, :, i], values[0, i], g[per * i:per * (i + 1)]

    def gap(self, a_st: Tensor, s: Surrogates, with_hvp: bool):
        """Eq. (talo_gap) on surrogates ``s`` built on the forward that produced ``a_st``:
        (g_ind, g_team, W_gap, grad W or None). Without SAIL each L_i depends on tree i
        alone (separable). In closed form where ``s`` holds its forward's tapes."""
        if s.taped is not None:
            return talo_gap_closed_form(s.taped, s.reference, self.layout, with_hvp)
        return talo_gap(s.L_ind, s.L_team, self.groups, separable=not self.uses_sail,
                        with_hvp=with_hvp, through=self.through(a_st))

    def individual_gradient(self, s: Surrogates) -> Tensor | None:
        """g_ind = [grad_{theta_i} L_i]_i of taped surrogates ``s`` (None without tapes)."""
        if s.taped is None:
            return None
        return gradient(s.taped, cotangent_sets(*s.taped.chain.sizes, s.reference, "ind"), self.layout)
