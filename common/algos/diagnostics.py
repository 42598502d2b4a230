"""The learner's mechanism diagnostics, measured the same way for every method.

- W_gap and cos(g_ind, g_team) (Eq. talo_gap, no HVP) on every minibatch, at the
  parameters before that minibatch's step, with the surrogates' ratios taken against
  the policy at the *update's start* (``rho_i = pi_theta / pi_theta_start``), not
  against the behaviour policy that collected the batch. The PPO surrogates the
  methods step along keep the behaviour policy's ratio (that is the algorithm); only
  the diagnostics change reference. So the first minibatch is at ratio 1 for every
  method whatever the policy lag, W_gap is exactly 0 there without SAIL's coupling
  (identity center: g_team = g_ind), and its growth over the update's epochs is what
  TALO regulates. ``gap_summary`` turns one update's trace into metrics-row entries.
- ``local_ab``: the local claim of Eq. (talo_condition) as a measurement: on a frozen
  minibatch, W_gap after a step of equal length along g_TALO and along g_ind.
- ``talo_condition``: does the step a TALO method applied meet Eq. (talo_condition)?
- ``qp_diagnostics``: the deployment correction ||Q_CBF(a_ST) - a_ST|| (Eq. qpshield).

See docs/interfaces.md for the full list of ``update`` diagnostics.
"""
from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from common.algos.batch import Minibatch
from common.algos.config import AlgoConfig
from common.algos.proposal_map import ProposalMap, StartPoint, Surrogates
from common.algos.talo import cosine, equal_length_ab, talo_project, unflatten_like
from common.shield.qp import solve_cbf_qp


def snapshot(params: list[Tensor]) -> list[Tensor]:
    return [p.detach().clone() for p in params]


def restore(params: list[Tensor], values: list[Tensor]) -> None:
    with torch.no_grad():
        for p, v in zip(params, values):
            p.copy_(v)


@dataclass
class GapAtStart:
    """W_gap and cos(g_ind, g_team) at a minibatch's parameters before its step (ratios
    against the update's start), and what they were computed from: the forward's a_ST, its
    surrogates ``start``, g_ind, W and, where the step took it, grad W. ``local_ab`` at the
    same parameters on the same minibatch reads them instead of a second forward, SAIL
    solve and (for the TALO methods, on-policy) HVP."""
    w_gap: float
    cos_ind_team: float
    a_st: Tensor
    start: Surrogates
    g_ind: Tensor
    w: Tensor
    grad_w: Tensor | None = None

    @classmethod
    def of(cls, g_ind: Tensor, g_team: Tensor, w: Tensor, a_st: Tensor, start: Surrogates,
           grad_w: Tensor | None = None) -> "GapAtStart":
        return cls(float(w), cosine(g_ind, g_team), a_st, start, g_ind, w, grad_w)

    @property
    def reusable(self) -> bool:
        """Taped surrogates hold their own copy of the forward; an autograd graph reads the
        live parameters, which the step has since moved."""
        return self.start.taped is not None


def gap_diagnostics(proposal: ProposalMap, mb: Minibatch, tau: float, kappa: float):
    """W_gap and cos(g_ind, g_team) (Eq. talo_gap, no HVP, ratios against the update's
    start) at the current parameters, for the sequential methods (the joint step
    measures them itself): a ``GapAtStart``. Also returns the ``StartPoint``, which the
    HAPPO step reuses: the forward (saves a SAIL solve) and its first carrier's surrogate."""
    a_st, step, behaviour, start = proposal.start_point(mb, tau, kappa)
    g_ind, g_team, w, _ = proposal.gap(a_st, start, with_hvp=False)
    g_behaviour = g_ind if start is behaviour else proposal.individual_gradient(behaviour)
    a_st = a_st.detach()   # the HAPPO step refreshes its copy block by block
    return GapAtStart.of(g_ind, g_team, w, a_st, start), StartPoint(a_st.clone(), step, behaviour, g_behaviour)


def logratio_at_start(data: Minibatch) -> float:
    """Mean |log pi_theta_start - log pi_behaviour| over the robot blocks: what the
    policy lag (and actor/learner rounding) put between the two references."""
    if not bool(data.active.any()):
        return 0.0
    return float((data.logp_start - data.logp_old)[data.active].abs().mean())


def local_ab(proposal: ProposalMap, cfg: AlgoConfig, mb: Minibatch, tau: float, kappa: float,
             length: float, at: list[Tensor] | None = None, gap: GapAtStart | None = None) -> dict[str, float]:
    """The local claim of Eq. (talo_condition) as a measurement, the same for every
    method: on the frozen minibatch ``mb`` at parameters ``at`` (default: the
    current ones), W_gap (ratios against the update's start, as the diagnostics)
    after a step of length ``length`` along g_TALO (Eq. talo_projection, ``cfg``'s
    sigma and eps) and along g_ind. Leaves the parameters as it found them.

    ``ab_w_before``, ``ab_w_talo``, ``ab_w_ind``, ``ab_ratio`` = ab_w_talo / ab_w_ind
    (< 1: TALO's direction kept the gap smaller; NaN where ab_w_ind = 0),
    ``ab_rate_talo``, ``ab_rate_ind`` (the first-order rates grad W . g / ||g|| of the
    two directions, what Eq. talo_condition is about; in the split parameters' blocks
    grad W is the straight-through surrogate, common/algos/talo.py),
    ``ab_corrected`` (Delta_gap > 0; else g_TALO = g_ind and the ratio is 1) and
    ``ab_step`` (the length). ``gap``: the update step's ``GapAtStart`` on ``mb`` at these
    parameters, whose forward (and grad W, where taken) is reused where it is taped."""
    params = proposal.params
    current = snapshot(params)
    try:
        if at is not None:
            restore(params, at)
        base = snapshot(params)
        if mb.logp_start is None:   # these parameters are the start: fix the reference here
            mb = dataclasses.replace(mb, logp_start=proposal.start_log_prob(mb, tau, kappa))
        if gap is not None and gap.reusable:
            a_st, start, g_ind, w0, grad_w = gap.a_st, gap.start, gap.g_ind, gap.w, gap.grad_w
        else:
            a_st, _, _, start = proposal.start_point(mb, tau, kappa)
            grad_w = None
        if grad_w is None:
            g_ind, _, w0, grad_w = proposal.gap(a_st, start, with_hvp=True)
        g_talo, delta = talo_project(g_ind, grad_w, w0, cfg.talo_sigma, cfg.talo_eps)

        def w_at(displacement: Tensor) -> float:
            restore(params, [b + d.to(b.dtype) for b, d in zip(base, unflatten_like(displacement, params))])
            a_st, _, _, start = proposal.start_point(mb, tau, kappa)
            return float(proposal.gap(a_st, start, with_hvp=False)[2])

        w_talo, w_ind = equal_length_ab(w_at, float(w0), g_talo, g_ind, length)
    finally:
        restore(params, current)

    def rate(g: Tensor) -> float:
        n = float(g.norm())
        return float(grad_w @ g) / n if n > 0 else 0.0

    return {"ab_w_before": float(w0), "ab_w_talo": w_talo, "ab_w_ind": w_ind,
            "ab_ratio": w_talo / w_ind if w_ind > 0 else math.nan,
            "ab_rate_talo": rate(g_talo), "ab_rate_ind": rate(g_ind),
            "ab_corrected": float(delta > 0.0), "ab_step": float(length)}


def talo_condition(cfg: AlgoConfig, params: list[Tensor], grad_w: Tensor, w_gap, g_ind: Tensor,
                   g_team: Tensor, before: list[Tensor], direct: bool) -> tuple[float, float, float]:
    """Does the step actually applied, delta = theta_after - theta_before (``params``
    now and ``before``), meet Eq. (talo_condition) to first order,
    grad W . delta <= -sigma W_gap eta?

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
    eta = cfg.talo_eta if direct else cfg.actor_lr
    gw = grad_w.detach().double()
    after = torch.cat([p.detach().reshape(-1) for p in params])
    start = torch.cat([b.reshape(-1) for b in before])
    delta = after.double() - start.double()
    lhs = float(gw @ delta)
    rhs = -cfg.talo_sigma * float(w_gap) * eta
    eps = torch.finfo(after.dtype).eps
    ulp = eps * torch.maximum(after.abs(), start.abs()).double()
    tol = 1e-6 * (abs(rhs) + float(gw.norm() * delta.norm())) + float(gw.abs() @ ulp)
    floor = 0.5 * (8.0 * torch.finfo(g_ind.dtype).eps * float(g_ind.norm() + g_team.norm())) ** 2
    at_floor = float(w_gap) <= floor
    return float(at_floor or lhs <= rhs + tol), float(lhs < 0.0), float(at_floor)


def qp_diagnostics(batch, n_samples: int) -> dict[str, float]:
    """``correction_st``: mean ||Q_CBF(a_ST) - a_ST|| (the deployment correction,
    Eq. qpshield applied to the raw tree action) and ``intervention_rate_st``
    (share with correction > 1e-6), on ``n_samples`` evenly spaced samples of the
    batch (``AlgoConfig.diag_qp_samples``; 0: none). Computed for every method; for
    unshielded HAPPO it is a probe only (its deployment runs no QP)."""
    n = int(n_samples)
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
