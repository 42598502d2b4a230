"""The numpy references of common/policy's numba kernels: test oracles, not production code.

Each function here is the same computation as one kernel-backed production function, written
in plain numpy (``reference.X`` mirrors the production function named in its docstring): the
team's tree forward (tests/test_tree_kernel.py), the proposal's sampling and log-density and the
human block substitution (tests/test_proposal_kernels.py), and the SAIL projection with its
line search and implicit step (tests/test_sail_kernel.py). Nothing in production imports this
module.
"""
from __future__ import annotations

from collections.abc import Mapping

import numpy as np

from common.policy import sail
from common.policy.proposal import _A_PROP_OUTSIDE, _LOG_SQRT_2PI, _NONFINITE_CENTER, ProposalConfig
from common.policy.proposal import _DEFAULT as _PROPOSAL_DEFAULT
from common.policy.proposal import _check, _n_agents, _sample_bound
from common.policy.rollout import _NONFINITE_HUMAN, _PARTIAL_BLOCK
from common.policy.sail import SailConfig
from common.policy.sail import _DEFAULT as _SAIL_DEFAULT
from common.policy.tree import _team_inputs, carrier_params, tree_forward_np


def team_forward(params: Mapping[str, np.ndarray], obs: np.ndarray):
    """``tree.team_forward_np``: each carrier's ``tree_forward_np``."""
    spec, obs = _team_inputs(params, obs)
    outs = [tree_forward_np(carrier_params(params, i), obs[:, i]) for i in range(spec.n_agents)]
    return (
        np.concatenate([o[0] for o in outs], axis=1),
        np.stack([o[1] for o in outs], axis=1),
        np.stack([o[2] for o in outs], axis=1),
        np.stack([o[3] for o in outs], axis=1),
    )


def _center_mu(center, config):
    """The pre-tanh mean atanh(center), the centre clipped to +-(1 - center_eps)."""
    lim = 1.0 - config.center_eps
    return np.arctanh(np.clip(center, -lim, lim))


def proposal_log_prob(center, log_std, a_prop, config: ProposalConfig = _PROPOSAL_DEFAULT) -> np.ndarray:
    """``proposal.proposal_log_prob_np``."""
    center = np.asarray(center, dtype=np.float64)
    log_std = np.asarray(log_std, dtype=np.float64)
    a = np.asarray(a_prop, dtype=np.float64)
    _check(center, log_std, a)
    if not (np.all(np.isfinite(a)) and np.all(np.abs(a) < 1.0)):
        raise ValueError(_A_PROP_OUTSIDE)
    n = _n_agents(center.shape[1], config.act_dim)
    mu = _center_mu(center, config)
    u = np.arctanh(a)
    z = (u - mu) * np.exp(-log_std)
    per_dim = -0.5 * z * z - log_std - _LOG_SQRT_2PI - (np.log1p(-a) + np.log1p(a))
    return per_dim.reshape(len(a), n, config.act_dim).sum(-1)


def proposal_sample(center, log_std, rng: np.random.Generator, config: ProposalConfig = _PROPOSAL_DEFAULT,
                                 human_carrier=None, human_action=None):
    """``proposal.proposal_sample_np`` (the same draws from ``rng``)."""
    center = np.asarray(center, dtype=np.float64)
    log_std = np.asarray(log_std, dtype=np.float64)
    _check(center, log_std)
    if not (np.all(np.isfinite(center)) and np.all(np.isfinite(log_std))):
        raise ValueError(_NONFINITE_CENTER)
    u = _center_mu(center, config) + np.exp(log_std) * rng.standard_normal(center.shape)
    bound = _sample_bound(config)
    a = np.clip(np.tanh(u).astype(np.float32), -bound, bound).astype(np.float64)
    logp = proposal_log_prob(center, log_std, a, config)
    if human_carrier is not None:
        fixed = np.repeat(np.asarray(human_carrier, dtype=bool), config.act_dim, axis=1)
        a = np.where(fixed, human_action, a)
        logp = np.where(human_carrier, 0.0, logp)
    return a, logp


def _carrier_fixed_mask(fixed_mask: np.ndarray, n_agents: int, act_dim: int) -> np.ndarray:
    """[B, N*A] bool column mask -> [B, N] per-carrier mask; raises if a block is only partly fixed."""
    blocks = fixed_mask.reshape(len(fixed_mask), n_agents, act_dim)
    whole = blocks.all(-1)
    if np.any(blocks.any(-1) != whole):
        raise ValueError(_PARTIAL_BLOCK)
    return whole


def human_blocks(a_tree: np.ndarray, fixed: np.ndarray, human: np.ndarray, n_agents: int):
    """``rollout.human_blocks``."""
    if np.any(fixed) and not np.all(np.isfinite(human[fixed])):
        raise ValueError(_NONFINITE_HUMAN)
    human_carrier = _carrier_fixed_mask(fixed, n_agents, a_tree.shape[1] // n_agents)
    return np.where(fixed, human, a_tree), human_carrier


def line_search(x, dx, a, Cn, cn, kappa):
    """argmin_{t >= 0} f(x + t dx): the root of the increasing piecewise-linear phi'(t) (the line
    search of ``sail_kernels.sail_newton``'s ``"exact"`` damping)."""
    r = cn - (Cn @ x[..., None])[..., 0]
    s = (Cn @ dx[..., None])[..., 0]
    g0, q = np.sum((x - a) * dx, -1), np.sum(dx * dx, -1)

    def dphi(t):  # [B,T] -> phi'(t) [B,T]
        h = np.maximum(r[:, None, :] - t[..., None] * s[:, None, :], 0.0)
        return g0[:, None] + t * q[:, None] - kappa[:, None] * np.sum(h * s[:, None, :], -1)

    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        tb = r / s
    valid = (s != 0) & (tb > 0)  # rows that switch on/off at a positive step
    tb = np.where(valid, tb, 0.0)
    neg = valid & (dphi(tb) < 0)
    lo = np.max(np.where(neg, tb, 0.0), -1)  # last breakpoint still descending
    hi = np.min(np.where(valid & ~neg, tb, np.inf), -1)
    mid = np.where(np.isfinite(hi), 0.5 * (lo + hi), lo + 1.0)
    on = (r - mid[:, None] * s) > 0  # rows penalized on (lo, hi), where phi' is linear
    slope = q + kappa * np.sum(np.where(on, s * s, 0.0), -1)
    t = lo - dphi(lo[:, None])[:, 0] / np.where(slope > 0, slope, 1.0)
    return np.where(slope > 0, np.clip(t, lo, hi), 1.0)


def sail_project(
    a_st,
    C,
    c,
    mask,
    kappa,
    n_newton: int | None = None,
    damping: str | None = None,
    fixed_mask=None,
    fixed_action=None,
    config: SailConfig = _SAIL_DEFAULT,
) -> np.ndarray:
    """``sail.sail_project_np`` in vectorized numpy, the row preparation included."""
    a, Cn, cn, keep, kappa, n_newton, damping = sail._prepare_np(
        a_st, C, c, mask, kappa, n_newton, damping, fixed_mask, fixed_action, config, compiled=False)
    eye = np.eye(a.shape[1])
    x = a.copy()
    todo = np.arange(len(a))  # samples not yet at their exact minimizer
    for _ in range(n_newton):
        if todo.size == 0:
            break
        xs, at, Ct, ct, kt, kap = x[todo], a[todo], Cn[todo], cn[todo], keep[todo], kappa[todo]
        resid = ct - (Ct @ xs[..., None])[..., 0]
        active = (resid > 0) & kt
        r = np.where(active, resid, 0.0)
        Ca = Ct * active[..., None]
        grad = (xs - at) - kap[:, None] * (r[:, None, :] @ Ct)[:, 0, :]
        H = eye + kap[:, None, None] * (Ca.transpose(0, 2, 1) @ Ca)
        dx = -np.linalg.solve(H, grad[..., None])[..., 0]
        # a full step that keeps the active set lands on the minimizer of this quadratic
        # piece, where grad f = 0: exact, so the sample is done
        exact = np.all(((ct - (Ct @ (xs + dx)[..., None])[..., 0] > 0) & kt) == active, axis=1)
        t = np.ones(len(todo))
        ls = ~exact if damping == "exact" else np.zeros(len(todo), dtype=bool)
        if ls.any():
            t[ls] = line_search(xs[ls], dx[ls], at[ls], Ct[ls], ct[ls], kap[ls])
        x[todo] = xs + t[:, None] * dx
        todo = todo[~exact]
    return x


def sail_implicit_step(x_star, C, c, mask, kappa, fixed_mask, fixed_action,
                                    config: SailConfig = _SAIL_DEFAULT):
    """``sail.sail_implicit_step_np``'s (H_inv, offset) at a given ``x_star`` in plain numpy."""
    _, Cn, cn, keep, kappa, _, _ = sail._prepare_np(
        x_star, C, c, mask, kappa, None, None, fixed_mask, fixed_action, config, compiled=False)
    r = cn - np.einsum("bmd,bd->bm", Cn, x_star)
    act = (r > 0) & keep
    Ca = Cn * act[..., None]
    H = np.eye(Cn.shape[-1]) + kappa[:, None, None] * np.einsum("bmd,bme->bde", Ca, Ca)
    offset = x_star - kappa[:, None] * np.einsum("bm,bmd->bd", np.where(act, r, 0.0), Cn)
    return np.linalg.inv(H), offset
