"""The surrogate chain in closed form: from the stacked tree actions a_ST and log_std to
the PPO surrogates L_1..L_N, L_team (Eq. ppo_surrogates) against one or two reference
policies, with its first and second derivatives written out.

What the learner differentiates between the trees and the surrogates is per sample and
small: the proposal center c is affine in a_ST (the SAIL map's implicit step, Eq.
sail_jacobian, c = x* - H^{-1} (offset - a): Jacobian H^{-1}; or the identity center),
the log-density of the stored a_prop is a sum over action dimensions of closed-form
terms in (c_k, log_std_k) (common/policy/proposal.py), and each surrogate is a mean over
samples of a clipped exponential of a log-ratio. As an autograd graph this is about a
thousand small ops on [B, 9] tensors per minibatch step, walked by every backward pass of
TALO's gap (the blocks of d, g_team, the diagnostics' gap) and again by the double
backward, each op costing the engine's per-op overhead rather than arithmetic. Here it is
one ``autograd.Function`` whose backward (``ChainVJP``) is differentiable once in closed
form (the Hessian-vector product), the pattern of ``tree_torch.TreeCore``; the figures
are in docs/scaling.md ("The learner's update, 2026-12-06 afternoon").

Notation per sample b, action dimension k of carrier j = k // 3 (center c_k, stored
a_k, mu_k = atanh(clip(c_k)), u_k = atanh(a_k), sigma_k = exp(log_std_k)):

    log pi_j = sum_k [-z_k^2 / 2 - log_std_k - log sqrt(2 pi) - log(1 - a_k^2)],  z_k = (u_k - mu_k) / sigma_k
    d log pi / d c_k = g_k = (z_k / sigma_k) mu'_k,   mu'_k = 1[|c_k| <= lim] / (1 - c_k^2)
    d log pi / d log_std_k = h_k = z_k^2 - 1

and with rho = exp(log_ratio) per carrier (rho_T = exp(sum_j log_ratio_j) for the team),
l(rho, A) = min(rho A, clip(rho) A) has d l / d log_ratio = coef(rho, A) rho with coef
piecewise constant (torch's tie rule for ``minimum`` and ``clamp``, so that the gradients
equal autograd's on the reference graph), hence d^2 l / d log_ratio^2 = coef rho.

tests/test_surrogate_chain.py checks values, gradients and Hessian-vector products against
``reference_surrogates`` (the same function as an autograd graph, which the learner used
before) on learner minibatches of every method that uses it, and TALO's whole gap.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor
from torch.autograd.function import once_differentiable

from common.algos import surrogate_kernels as kernels
from common.policy.proposal import ProposalConfig, density_terms, proposal_log_prob


def clipped(ratio: Tensor, adv: Tensor, clip: float) -> Tensor:
    """l(rho, A) = min(rho A, clip(rho, 1-eps, 1+eps) A) (Eq. ppo_surrogates)."""
    return torch.minimum(ratio * adv, ratio.clamp(1 - clip, 1 + clip) * adv)


def surrogate_values(log_ratio: Tensor, adv: Tensor, active: Tensor, clip: float) -> Tensor:
    """[L_1 .. L_N, L_team] (Eq. ppo_surrogates; team ratio = product over the robot carriers)."""
    per = clipped(log_ratio.exp(), adv[:, None], clip) * active
    return torch.cat([per.mean(0), clipped(log_ratio.sum(1).exp(), adv, clip).mean()[None]])


def center_value(a_st: Tensor, fixed: Tensor, a_prop: Tensor, step) -> Tensor:
    """The proposal center from a_ST: SAIL's implicit step (``step`` a ``SailStep``) or the
    identity (``step`` None); human blocks at their measured action. The same expressions
    as ``ProposalMap.center``, so the same bits."""
    if step is None:
        return torch.where(fixed, a_prop.to(a_st.dtype), a_st)
    a = torch.where(fixed, a_prop.double(), a_st.double())
    return step.x_star - (step.H_inv @ (step.offset - a)[..., None])[..., 0]


def _numpy(x: Tensor):
    return x.detach().double().contiguous().numpy()


@dataclass(frozen=True)
class ChainTape:
    """What the chain's derivatives read at one forward (``chain_forward``): the kernels'
    per-sample constants, the active robot blocks, SAIL's H^{-1} (empty: identity center)
    and the robot columns. ``vjp`` and ``hvp`` take output cotangent sets ``gbars``
    [G, R, N+1] (G = 1: one for every column; G = N: set j for carrier j's columns)."""
    constants: tuple
    active: np.ndarray
    H_inv: np.ndarray
    robot: np.ndarray

    @property
    def sizes(self) -> tuple[int, int]:
        """(R, N): reference policies and carriers."""
        R, _, N = self.constants[6].shape
        return R, N

    def vjp(self, gbars: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Cotangents of (a_ST [B,D], log_std [D])."""
        _, _, _, g, h, _, w_ind, w_team = self.constants
        return kernels.chain_vjp(gbars, g, h, w_ind, w_team, self.H_inv, self.robot)

    def hvp(self, gbars: np.ndarray, v_a: np.ndarray, v_s: np.ndarray):
        """``vjp``'s derivative along (v_a [B,D], v_s [D]): (d/dgbars, Hessian times v in a_ST, in log_std)."""
        return kernels.chain_hvp(gbars, v_a, v_s, *self.constants, self.active, self.H_inv, self.robot)


def chain_forward(a_st, log_std, fixed, a_prop, a_robot, terms, step, references, adv, active, clip, config):
    """Surrogates [R, N+1], log-ratios [R, B, N] (the reference's own expressions, so the same
    bits) and the ``ChainTape`` of their derivatives; no autograd graph."""
    with torch.no_grad():
        center = center_value(a_st, fixed, a_prop, step)
        logp = proposal_log_prob(center, log_std, a_robot, config, terms=terms)
        values, log_ratios = surrogates_of_log_density(logp, references, adv, active, clip)
    active_np = active.contiguous().numpy()
    constants = kernels.chain_constants(_numpy(center), _numpy(log_std), _numpy(terms[0]), _numpy(log_ratios),
                                        _numpy(adv), active_np, float(clip), 1.0 - config.center_eps)
    H_inv = np.empty((0, 0, 0)) if step is None else _numpy(step.H_inv)
    return values, log_ratios, ChainTape(constants, active_np, H_inv, (~fixed).contiguous().numpy())


class SurrogateChain(torch.autograd.Function):
    """(a_ST [B,D], log_std [D]) -> surrogates [R, N+1] = [L_1..L_N, L_team] per reference
    policy, and the log-ratios [R, B, N] (not differentiable). ``references``: R log-densities
    [B, N] of the stored a_prop to take ratios against, None for this forward's own (ratio 1).
    The values are the reference's own expressions; the derivatives come from the kernels
    of common/algos/surrogate_kernels.py."""

    @staticmethod
    def forward(ctx, a_st, log_std, fixed, a_prop, a_robot, terms, step, references, adv, active, clip, config):
        values, log_ratios, ctx.tape = chain_forward(a_st, log_std, fixed, a_prop, a_robot, terms, step,
                                                     references, adv, active, clip, config)
        ctx.save_for_backward(a_st, log_std)
        ctx.mark_non_differentiable(log_ratios)
        return values, log_ratios

    @staticmethod
    def backward(ctx, gbar, _):
        if gbar is None:
            return (None,) * 12
        return (*ChainVJP.apply(gbar, *ctx.saved_tensors, ctx.tape),) + (None,) * 10


class ChainVJP(torch.autograd.Function):
    """The cotangents of (a_ST, log_std) for output cotangents gbar [R, N+1]; its backward
    along a direction (V_a [B,D], V_s [D]) is the double backward: d/dgbar = the directional
    derivative of the surrogates, d/d(a_ST, log_std) = the chain's Hessian times V. a_ST and
    log_std are inputs (the kernels read them through ``tape``) so that autograd routes
    those terms to them."""

    @staticmethod
    def forward(ctx, gbar, a_st, log_std, tape):
        ctx.tape, ctx.gbars, ctx.dtypes = tape, _numpy(gbar)[None], (gbar.dtype, a_st.dtype, log_std.dtype)
        a_bar, s_bar = tape.vjp(ctx.gbars)
        return torch.from_numpy(a_bar).to(a_st.dtype), torch.from_numpy(s_bar).to(log_std.dtype)

    @staticmethod
    @once_differentiable
    def backward(ctx, v_a, v_s):
        B, D = ctx.tape.constants[3].shape
        v_a = np.zeros((B, D)) if v_a is None else _numpy(v_a)
        v_s = np.zeros(D) if v_s is None else _numpy(v_s)
        dgbar, h_a, h_s = ctx.tape.hvp(ctx.gbars, v_a, v_s)
        return (*(torch.from_numpy(x).to(dt) for x, dt in zip((dgbar[0], h_a, h_s), ctx.dtypes)), None)


def chain_surrogates(a_st: Tensor, log_std: Tensor, mb, step, references, clip: float,
                     config: ProposalConfig = ProposalConfig()) -> tuple[Tensor, Tensor]:
    """Surrogates [R, N+1] and log-ratios [R, B, N] of minibatch ``mb`` (a ``Minibatch``) at
    a_ST against ``references`` (R log-densities [B, N], None: this forward's own), by
    ``SurrogateChain``; ``step``: SAIL's implicit step, None for the identity center."""
    a_robot = mb.a_robot
    terms = mb.density_terms or density_terms(a_robot, config)
    return SurrogateChain.apply(a_st, log_std, mb.fixed, mb.a_prop, a_robot, terms, step, tuple(references),
                                mb.adv, mb.active, float(clip), config)


def chain_surrogates_taped(a_st: Tensor, log_std: Tensor, mb, step, references, clip: float,
                           config: ProposalConfig = ProposalConfig()) -> tuple[Tensor, Tensor, ChainTape]:
    """``chain_surrogates``' values without a graph, and the ``ChainTape`` their closed-form
    derivatives read (common/algos/gap_closed_form.py)."""
    a_robot = mb.a_robot
    terms = mb.density_terms or density_terms(a_robot, config)
    return chain_forward(a_st.detach(), log_std.detach(), mb.fixed, mb.a_prop, a_robot, terms, step,
                         tuple(references), mb.adv, mb.active, float(clip), config)


def surrogates_of_log_density(logp: Tensor, references, adv: Tensor, active: Tensor,
                              clip: float) -> tuple[Tensor, Tensor]:
    """Surrogates [R, N+1] and log-ratios [R, B, N] from the log-density ``logp`` [B, N] of
    the stored a_prop, as an autograd graph (references as in ``chain_surrogates``)."""
    refs = torch.stack([logp.detach() if r is None else r.to(logp.dtype) for r in references])
    log_ratios = torch.where(active, logp - refs, torch.zeros_like(logp))
    values = torch.stack([surrogate_values(r, adv, active, clip) for r in log_ratios])
    return values, log_ratios


def reference_surrogates(a_st: Tensor, log_std: Tensor, mb, step, references, clip: float,
                         config: ProposalConfig = ProposalConfig()) -> tuple[Tensor, Tensor]:
    """``chain_surrogates`` as one autograd graph: what the closed form is tested against."""
    logp = proposal_log_prob(center_value(a_st, mb.fixed, mb.a_prop, step), log_std, mb.a_robot, config,
                             terms=mb.density_terms)
    return surrogates_of_log_density(logp, references, mb.adv, mb.active, clip)
