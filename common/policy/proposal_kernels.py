"""Numba kernels of the actor's proposal step (common/policy/proposal.py,
common/policy/rollout.py): the human blocks, the squashed-Gaussian sample and
its exact log-density, one pass over the batch each instead of numpy's dozen
calls per step (they were most of ``propose`` at an actor's 16 envs).

Their numpy references are ``reference.proposal_sample``, ``reference.proposal_log_prob``
and ``reference.human_blocks`` (common/policy/reference.py);
tests/test_proposal_kernels.py compares them. The noise is drawn by the caller
(``rng.standard_normal``, the same draws in the same order as the reference), so
a kernel and its reference see the same random numbers. ``math`` and numpy's
vectorized ``tanh``/``arctanh``/``log1p`` may differ in the last bit, so the
comparison is to rounding (and a sample rounded to float32 may in rare cases
land one float32 step apart).

Errors are returned as codes (``OK`` or one of the others below) for the
caller to raise with its message: a kernel stops at the first bad entry.
``nogil``: in-process, the actor's step runs beside the learner's thread.
"""
from __future__ import annotations

import math

import numpy as np
from numba import njit

OK = 0
NONFINITE = 1        # a center or log_std entry of a sampled block is NaN/Inf
PARTIAL_BLOCK = 2    # a carrier block is only partly fixed
NONFINITE_HUMAN = 3  # a fixed (human) entry is NaN/Inf
OUTSIDE_BOX = 4      # a stored proposal is NaN/Inf or not inside the open box (-1, 1)

LOG_SQRT_2PI = 0.5 * math.log(2.0 * math.pi)


@njit(cache=True, inline="always")
def _clip(x, lim):
    """``np.clip(x, -lim, lim)`` of a float (NaN propagates)."""
    if x != x:
        return x
    return -lim if x < -lim else (lim if x > lim else x)


@njit(cache=True, inline="always")
def _log_density(a, mu, log_std):
    """log N(atanh a; mu, sigma) - log(1 - a^2), the reference's formula term by term."""
    z = (math.atanh(a) - mu) * math.exp(-log_std)
    return -0.5 * z * z - log_std - LOG_SQRT_2PI - (math.log1p(-a) + math.log1p(a))


@njit(cache=True, nogil=True)
def human_blocks(a_tree, fixed, human, act_dim):
    """a_tree [B,d] f64, fixed [B,d] bool, human [B,d] f64 (broadcast views are fine).
    Returns (a_st [B,d]: the human's action on fixed entries, the tree's elsewhere;
    human_carrier [B,N] bool: the carrier's whole block is fixed; error code)."""
    B, d = a_tree.shape
    N = d // act_dim
    a_st = np.empty((B, d))
    human_carrier = np.zeros((B, N), dtype=np.bool_)
    for s in range(B):
        for i in range(N):
            n_fixed = 0
            for j in range(act_dim):
                if fixed[s, i * act_dim + j]:
                    n_fixed += 1
            if n_fixed != 0 and n_fixed != act_dim:
                return a_st, human_carrier, PARTIAL_BLOCK
            human_carrier[s, i] = n_fixed == act_dim
            for j in range(act_dim):
                k = i * act_dim + j
                if n_fixed:
                    h = human[s, k]
                    if not math.isfinite(h):
                        return a_st, human_carrier, NONFINITE_HUMAN
                    a_st[s, k] = h
                else:
                    a_st[s, k] = a_tree[s, k]
    return a_st, human_carrier, OK


@njit(cache=True, nogil=True)
def sample_proposal(center, log_std, noise, human_carrier, human, center_eps, bound, act_dim):
    """center [B,d], log_std [1,d] or [B,d], noise [B,d] standard normal draws,
    human_carrier [B,N] bool, human [B,d] (read where human_carrier). Returns
    (a_prop [B,d]: tanh(mu + sigma noise) rounded to float32 and clipped to
    +-bound, the human's action in human blocks; logp [B,N]: the exact log-density
    of the stored a_prop, 0 in human blocks; error code). ``bound`` is a float32 value."""
    B, d = center.shape
    N = d // act_dim
    lim = 1.0 - center_eps
    per_sample = log_std.shape[0] > 1
    a_prop = np.empty((B, d))
    logp = np.zeros((B, N))
    for s in range(B):
        r = s if per_sample else 0
        for i in range(N):
            if human_carrier[s, i]:
                for j in range(act_dim):
                    a_prop[s, i * act_dim + j] = human[s, i * act_dim + j]
                continue
            acc = 0.0
            for j in range(act_dim):
                k = i * act_dim + j
                c, ls = center[s, k], log_std[r, k]
                if not (math.isfinite(c) and math.isfinite(ls)):
                    return a_prop, logp, NONFINITE
                mu = math.atanh(_clip(c, lim))
                a = np.float64(np.float32(math.tanh(mu + math.exp(ls) * noise[s, k])))
                a = _clip(a, bound)
                a_prop[s, k] = a
                acc += _log_density(a, mu, ls)
            logp[s, i] = acc
    return a_prop, logp, OK


@njit(cache=True, nogil=True)
def proposal_log_prob(center, log_std, a_prop, center_eps, act_dim):
    """Exact log-density per carrier [B,N] of a_prop [B,d] around center [B,d],
    log_std [1,d] or [B,d] (the same terms as ``sample_proposal``'s)."""
    B, d = center.shape
    N = d // act_dim
    lim = 1.0 - center_eps
    per_sample = log_std.shape[0] > 1
    logp = np.zeros((B, N))
    for s in range(B):
        r = s if per_sample else 0
        for i in range(N):
            acc = 0.0
            for j in range(act_dim):
                k = i * act_dim + j
                a = a_prop[s, k]
                if not (math.isfinite(a) and abs(a) < 1.0):
                    return logp, OUTSIDE_BOX
                acc += _log_density(a, math.atanh(_clip(center[s, k], lim)), log_std[r, k])
            logp[s, i] = acc
    return logp, OK
