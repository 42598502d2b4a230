"""Bounded per-carrier proposal around the SAIL center (Sec. III-C, Eq. action_chain).

Choice: a tanh-squashed diagonal Gaussian.

    mu = atanh(clip(center, -(1-center_eps), 1-center_eps)),   u ~ N(mu, diag(exp(log_std))^2),
    a_prop = tanh(u)   (then rounded to float32 and clipped to +-(1-sample_clip)).

Why: the support is the open box (-1,1)^d with positive density everywhere inside it,
so the likelihood ratio at any stored proposal is well defined, and the log-density
is exact in closed form by change of variables:

    log pi(a) = sum_k [ log N(atanh a_k; mu_k, sigma_k) - log(1 - a_k^2) ].

The SAIL center is unconstrained in R^d and may lie outside the box: it is clipped
to +-(1-center_eps) before atanh, i.e. an outside center proposes as if it sat just
inside the nearest face (|mu| <= atanh(1-1e-3) ~ 3.8). Clipping has zero gradient
outside that range, so a center pushed outside the box passes no gradient through
that coordinate (log_std still gets one). With a hard-tree center a_ST = tanh(.)
and SAIL off, atanh(center) undoes the tree's tanh, so the chain stays well
conditioned.

Stored proposals: samples are rounded to float32 (the wire/storage dtype) and
clipped to +-(1-sample_clip) so atanh stays finite, and the returned log-prob is
evaluated at exactly that stored value, in float64, by the same formula the
learner uses (`proposal_log_prob`), so behaviour and learner log-probs agree.
Clipping only changes samples with |u| > atanh(1-1e-6) ~ 7.25, i.e. > 3.4
standard deviations beyond the farthest center for sigma <= 1.

The joint density factorizes across carriers (independent noise), so log-probs
are returned per carrier [B,N], each the sum over that carrier's `act_dim` dims.

Entropy: the squashed Gaussian has no closed-form entropy. `proposal_entropy`
returns the pre-tanh Gaussian entropy (exact, depends on log_std only; an upper
bound on the squashed entropy because log|da/du| = log(1 - tanh(u)^2) <= 0), and,
if a center is given, adds a reparameterized Monte Carlo estimate of the expected
log-Jacobian E[sum log(1 - tanh(u)^2)], which makes it an unbiased estimate of
the squashed entropy.

torch is imported inside the torch functions only (actors never load torch).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from common.policy import proposal_kernels as kernels


@dataclass(frozen=True)
class ProposalConfig:
    center_eps: float = 1e-3    # center clipped to +-(1-center_eps) before atanh
    sample_clip: float = 1e-6   # stored samples clipped to +-(1-sample_clip)
    act_dim: int = 3            # dims per carrier (the per-carrier log-prob sums these)


_DEFAULT = ProposalConfig()
_LOG_SQRT_2PI = kernels.LOG_SQRT_2PI
_A_PROP_OUTSIDE = "proposal: a_prop must be finite with |a| < 1 (density is zero outside the open box)"
_NONFINITE_CENTER = "proposal: center and log_std must be finite"


def _n_agents(d: int, act_dim: int) -> int:
    if d % act_dim:
        raise ValueError(f"proposal: action dim {d} is not a multiple of act_dim={act_dim}")
    return d // act_dim


def _check(center, log_std, a_prop=None):
    if center.ndim != 2:
        raise ValueError(f"proposal: center must be [B,d], got shape {tuple(center.shape)}")
    if tuple(log_std.shape) not in ((center.shape[1],), tuple(center.shape)):
        raise ValueError(f"proposal: log_std must be [d] or [B,d] with d={center.shape[1]}, got {tuple(log_std.shape)}")
    if a_prop is not None and tuple(a_prop.shape) != tuple(center.shape):
        raise ValueError(f"proposal: a_prop shape {tuple(a_prop.shape)} != center shape {tuple(center.shape)}")


def _sample_bound(config: ProposalConfig) -> float:
    # largest float32 value <= 1 - sample_clip, so stored float32 samples are clipped losslessly
    bound = np.float32(1.0 - config.sample_clip)
    if bound > 1.0 - config.sample_clip:
        bound = np.nextafter(bound, np.float32(0.0))
    return float(bound)


# ----------------------------------------------------------------------------- numpy (actors)


def _log_std_rows(log_std: np.ndarray) -> np.ndarray:
    """log_std [d] or [B,d] as the kernels read it: [1,d] or [B,d] float64."""
    return np.ascontiguousarray(log_std.reshape(1, -1) if log_std.ndim == 1 else log_std)


def proposal_log_prob_np(center, log_std, a_prop, config: ProposalConfig = _DEFAULT) -> np.ndarray:
    """Exact log-density of a_prop [B,d] (|a| < 1) per carrier -> [B,N] (float64).
    The compiled kernel (common/policy/proposal_kernels.py); ``reference.proposal_log_prob``
    (common/policy/reference.py) is its numpy twin."""
    center = np.asarray(center, dtype=np.float64)
    log_std = np.asarray(log_std, dtype=np.float64)
    a = np.asarray(a_prop, dtype=np.float64)
    _check(center, log_std, a)
    _n_agents(center.shape[1], config.act_dim)
    logp, error = kernels.proposal_log_prob(np.ascontiguousarray(center), _log_std_rows(log_std),
                                            np.ascontiguousarray(a), config.center_eps, config.act_dim)
    if error != kernels.OK:
        raise ValueError(_A_PROP_OUTSIDE)
    return logp


def proposal_sample_np(center, log_std, rng: np.random.Generator, config: ProposalConfig = _DEFAULT,
                       human_carrier=None, human_action=None):
    """Sample a_prop [B,d] around the center and return (a_prop, logp [B,N]).

    a_prop is float64 holding float32-representable values inside +-(1-sample_clip);
    logp is evaluated exactly at those stored values. ``human_carrier`` [B,N] bool
    (optional): those carrier blocks take ``human_action`` [B,d] and log-prob 0
    (the noise is drawn for every entry all the same, so the stream does not
    depend on who holds a block). The compiled kernel
    (common/policy/proposal_kernels.py); ``reference.proposal_sample`` is its numpy twin.
    """
    center = np.asarray(center, dtype=np.float64)
    log_std = np.asarray(log_std, dtype=np.float64)
    _check(center, log_std)
    B, d = center.shape
    n = _n_agents(d, config.act_dim)
    noise = rng.standard_normal(center.shape)
    if human_carrier is None:
        human_carrier, human_action = np.zeros((B, n), dtype=bool), center
    a, logp, error = kernels.sample_proposal(
        np.ascontiguousarray(center), _log_std_rows(log_std), noise, human_carrier,
        np.asarray(human_action, dtype=np.float64), config.center_eps, _sample_bound(config), config.act_dim)
    if error != kernels.OK:
        raise ValueError(_NONFINITE_CENTER)
    return a, logp


# ----------------------------------------------------------------------------- torch (learner)


def density_terms(a_prop, config: ProposalConfig = _DEFAULT):
    """What the log-density takes from the stored a_prop alone [B,d] (float64): atanh(a)
    and the change of variables log(1 - a^2) (as log1p(-a) + log1p(a)). The learner computes
    them once per batch and passes them to every ``proposal_log_prob`` of its minibatches."""
    import torch

    a = torch.as_tensor(a_prop, dtype=torch.float64)
    if not bool((torch.isfinite(a) & (a.abs() < 1.0)).all()):
        raise ValueError(_A_PROP_OUTSIDE)
    return torch.atanh(a), torch.log1p(-a) + torch.log1p(a)


def proposal_log_prob(center, log_std, a_prop, config: ProposalConfig = _DEFAULT, terms=None):
    """Torch twin of `proposal_log_prob_np`: [B,N] float64, differentiable in center and log_std.

    Computed in float64 whatever the input dtype, because atanh/log(1-a^2) near the box
    faces lose digits in float32 (1 - a is ~1e-6 there). ``terms``: ``density_terms(a_prop)``
    if already computed (the same values; a_prop is then only checked for its shape).
    """
    import torch

    _check(center, log_std, a_prop)
    center, log_std = center.to(torch.float64), log_std.to(torch.float64)
    u, log_jac = density_terms(a_prop, config) if terms is None else terms
    n = _n_agents(center.shape[1], config.act_dim)
    lim = 1.0 - config.center_eps
    mu = torch.atanh(center.clamp(-lim, lim))
    z = (u - mu) * torch.exp(-log_std)
    per_dim = -0.5 * z * z - log_std - _LOG_SQRT_2PI - log_jac
    return per_dim.reshape(u.shape[0], n, config.act_dim).sum(-1)


def proposal_entropy(log_std, center=None, n_samples: int = 16, generator=None, config: ProposalConfig = _DEFAULT):
    """Per-carrier entropy (torch, differentiable).

    center None: pre-tanh Gaussian entropy sum_k (1/2 log(2 pi e) + log_std_k) -> [N]
    (exact for u, an upper bound for a = tanh(u)).
    center [B,d]: that plus a reparameterized Monte Carlo estimate (n_samples draws) of
    E[sum_k log(1 - tanh(u_k)^2)] -> [B,N], an unbiased estimate of the squashed entropy.
    """
    import torch

    d = log_std.shape[-1]
    n = _n_agents(d, config.act_dim)
    gauss = (0.5 + _LOG_SQRT_2PI + log_std).reshape(*log_std.shape[:-1], n, config.act_dim).sum(-1)
    if center is None:
        return gauss
    lim = 1.0 - config.center_eps
    mu = torch.atanh(center.clamp(-lim, lim))
    eps = torch.randn((n_samples, *center.shape), generator=generator, dtype=center.dtype, device=center.device)
    u = mu + torch.exp(log_std) * eps
    log_jac = 2.0 * (math.log(2.0) - u - torch.nn.functional.softplus(-2.0 * u))  # log(1 - tanh(u)^2), stable
    log_jac = log_jac.mean(0).reshape(center.shape[0], n, config.act_dim).sum(-1)
    return gauss + log_jac
