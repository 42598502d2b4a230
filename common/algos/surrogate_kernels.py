"""Numba kernels of the surrogate chain's derivatives (common/algos/surrogate_chain.py):
per sample, from the proposal center to the surrogates, everything is a handful of scalars
per action dimension and one D x D product with SAIL's H^{-1}; as torch ops on [B, 9]
tensors each line cost 5-100 us of per-op overhead, as one pass over the samples it is a
few microseconds per hundred samples. The formulas are those of the chain's docstring.
Float64, one core, ``nogil`` (the learner thread leaves the interpreter lock to the
actor's while they run). tests/test_surrogate_chain.py checks them, through
``SurrogateChain``, against autograd on the reference graph."""
from __future__ import annotations

import math

import numpy as np
from numba import njit

ACT = 3   # action dimensions per carrier (common.spec.CARRIER_ACT_DIM; tested equal)


@njit(cache=True, inline="always")
def _slope(ratio, adv, clip):
    """d min(rho A, clip(rho) A) / d rho as autograd computes it on ``surrogate_chain.clipped``:
    ``minimum`` sends a tie half to each side, ``clamp`` passes the gradient on its closed range."""
    x1 = ratio * adv
    x2 = min(max(ratio, 1.0 - clip), 1.0 + clip) * adv
    in_range = 1.0 if (ratio >= 1.0 - clip and ratio <= 1.0 + clip) else 0.0
    tie = 0.5 if x1 == x2 else 0.0
    return adv * ((1.0 if x1 < x2 else 0.0) + tie) + adv * in_range * ((1.0 if x1 > x2 else 0.0) + tie)


@njit(cache=True, nogil=True)
def chain_constants(center, log_std, u, log_ratios, adv, active, clip, lim):
    """What the derivatives read, per sample (``u`` = atanh of the stored a_prop): mu'_k and
    mu''_k of the clipped atanh, z_k, d log pi / d c_k (g), d log pi / d log_std_k (h), and
    the surrogates' slopes in log pi per reference r, individual ``w_ind`` [R,B,N] and team
    ``w_team`` [R,B,N]."""
    B, D = center.shape
    R, _, N = log_ratios.shape
    inv_sigma = np.exp(-log_std)
    mu1, mu2, z = np.empty((B, D)), np.empty((B, D)), np.empty((B, D))
    g, h = np.empty((B, D)), np.empty((B, D))
    w_ind = np.empty((R, B, N))
    w_team = np.empty((R, B, N))
    for b in range(B):
        for k in range(D):
            c = center[b, k]
            cc = min(max(c, -lim), lim)
            m1 = 1.0 / (1.0 - cc * cc) if (c >= -lim and c <= lim) else 0.0
            mu1[b, k] = m1
            mu2[b, k] = 2.0 * cc * m1 * m1
            zk = (u[b, k] - math.atanh(cc)) * inv_sigma[k]
            z[b, k] = zk
            g[b, k] = zk * inv_sigma[k] * m1
            h[b, k] = zk * zk - 1.0
        for r in range(R):
            total = 0.0
            for j in range(N):
                total += log_ratios[r, b, j]
                rho = math.exp(log_ratios[r, b, j])
                w_ind[r, b, j] = (_slope(rho, adv[b], clip) * rho / B) if active[b, j] else 0.0
            rho_t = math.exp(total)
            team = _slope(rho_t, adv[b], clip) * rho_t / B
            for j in range(N):
                w_team[r, b, j] = team if active[b, j] else 0.0
    return mu1, mu2, z, g, h, inv_sigma, w_ind, w_team


@njit(cache=True, inline="always")
def _weight(gbar, w_ind, w_team, b, j):
    """d (sum_o gbar_o L_o) / d log pi_{b,j}."""
    R, N = w_ind.shape[0], w_ind.shape[2]
    s = 0.0
    for r in range(R):
        s += gbar[r, j] * w_ind[r, b, j] + gbar[r, N] * w_team[r, b, j]
    return s


@njit(cache=True, inline="always")
def _from_center(cbar, H_inv, robot, b, out, lo, hi):
    """out[b, lo:hi] += (robot * J^T cbar)[lo:hi] (J = H^{-1}, or the identity when H_inv is empty)."""
    D = cbar.shape[0]
    for k in range(lo, hi):
        if H_inv.shape[0] == 0:
            s = cbar[k]
        else:
            s = 0.0
            for i in range(D):
                s += H_inv[b, i, k] * cbar[i]
        if robot[b, k]:
            out[b, k] += s


@njit(cache=True, inline="always")
def _block(G, gi, D):
    """The output columns cotangent set ``gi`` of ``G`` serves: all of them (G = 1) or carrier gi's."""
    return (0, D) if G == 1 else (ACT * gi, ACT * (gi + 1))


@njit(cache=True, nogil=True)
def chain_vjp(gbars, g, h, w_ind, w_team, H_inv, robot):
    """The cotangents of a_ST [B,D] and log_std [D] for output cotangents ``gbars`` [G, R, N+1]:
    G = 1, one set for every column; G = N, set j for carrier j's columns only (the blocks
    [grad_{z_j} L^(j)]_j of TALO's d with L^(j) = sum gbars[j] . L, in one pass)."""
    B, D = g.shape
    G = gbars.shape[0]
    a_bar = np.zeros((B, D))
    s_bar = np.zeros(D)
    cbar = np.empty(D)
    for b in range(B):
        for gi in range(G):
            lo, hi = _block(G, gi, D)
            for k in range(D):
                w = _weight(gbars[gi], w_ind, w_team, b, k // ACT)
                cbar[k] = w * g[b, k]
                if k >= lo and k < hi:
                    s_bar[k] += w * h[b, k]
            _from_center(cbar, H_inv, robot, b, a_bar, lo, hi)
    return a_bar, s_bar


@njit(cache=True, nogil=True)
def chain_hvp(gbars, v_a, v_s, mu1, mu2, z, g, h, inv_sigma, w_ind, w_team, active, H_inv, robot):
    """``chain_vjp``'s derivative along (v_a [B,D], v_s [D]) (with G = N, set j sees v only on
    carrier j's columns, as its block of ``chain_vjp`` reads): d/dgbars [G, R, N+1] (the
    surrogates' directional derivatives) and the chain's Hessian times v in a_ST [B,D] and
    log_std [D], summed over the sets."""
    B, D = g.shape
    G = gbars.shape[0]
    R, _, N = w_ind.shape
    dgbar = np.zeros((G, R, N + 1))
    h_a = np.zeros((B, D))
    h_s = np.zeros(D)
    dc = np.empty(D)
    va = np.empty(D)
    vs = np.empty(D)
    dlogp = np.empty(N)
    cbar = np.empty(D)
    for b in range(B):
        for gi in range(G):
            gbar = gbars[gi]
            lo, hi = _block(G, gi, D)
            for k in range(D):
                inside = k >= lo and k < hi
                va[k] = v_a[b, k] if (inside and robot[b, k]) else 0.0
                vs[k] = v_s[k] if inside else 0.0
            for k in range(D):                       # d c = J (robot * v_a)
                if H_inv.shape[0] == 0:
                    dc[k] = va[k]
                else:
                    s = 0.0
                    for i in range(D):
                        s += H_inv[b, k, i] * va[i]
                    dc[k] = s
            dteam = 0.0
            for j in range(N):
                s = 0.0
                for k in range(ACT * j, ACT * (j + 1)):
                    s += g[b, k] * dc[k] + h[b, k] * vs[k]
                dlogp[j] = s
                if active[b, j]:
                    dteam += s
            for r in range(R):
                for j in range(N):
                    dgbar[gi, r, j] += w_ind[r, b, j] * dlogp[j]
                    dgbar[gi, r, N] += w_team[r, b, j] * dlogp[j]
            for j in range(N):
                # d of the slopes: d(coef rho) = coef rho d log_ratio (coef piecewise constant)
                dw = 0.0
                for r in range(R):
                    dw += gbar[r, j] * w_ind[r, b, j] * dlogp[j] + gbar[r, N] * w_team[r, b, j] * dteam
                w = _weight(gbar, w_ind, w_team, b, j)
                for k in range(ACT * j, ACT * (j + 1)):
                    s_k = z[b, k] * inv_sigma[k]
                    ds_k = -mu1[b, k] * dc[k] * inv_sigma[k] * inv_sigma[k] - 2.0 * s_k * vs[k]
                    dg = ds_k * mu1[b, k] + s_k * mu2[b, k] * dc[k]
                    dz = -mu1[b, k] * dc[k] * inv_sigma[k] - z[b, k] * vs[k]
                    cbar[k] = dw * g[b, k] + w * dg
                    h_s[k] += dw * h[b, k] + w * 2.0 * z[b, k] * dz
            _from_center(cbar, H_inv, robot, b, h_a, 0, D)
    return dgbar, h_a, h_s
