"""Numba kernels of the learner's hard-tree forward and its analytic first and second
derivatives (Eqs. hard_gate, hard_tree_policy, st_gate), for ``tree_torch.TreeCore``.

The part of the tree they cover is what autograd spends its time on: from the unit
split vectors ``w`` [N, I, O], thresholds ``b`` [N, I], leaf gains ``K`` [N, L, A, O] and
offsets ``beta`` [N, L, A] (all float64, the straight-through top-k and the
normalization already applied by torch) to the mixed leaf output

    mix(o) = sum_l weight_l(m) tanh(K_l o + beta_l),   m_k = w_k . o - b_k,

whose value is tanh(u_{l*}) at the hard-routed leaf l*. ``weight_l`` is the path product
of g^ST (right) or 1 - g^ST (left), g^ST = 1[m > 0] + sigmoid(m / tau) - sg(...)
(Eq. st_gate): its value is one-hot, and its derivatives are those of the sigmoid
factors with every other factor at its hard value. So a leaf's weight has a non-zero
derivative in m_k only if its path leaves the hard route at most at k ("mismatches": the
levels where the leaf's direction is not the hard one), and a non-zero second
derivative in (m_k, m_k') only if it leaves it at most at k and k'. Per sample the first
derivatives need the hard leaf and the D leaves one mismatch away, the second ones the
leaves at most two away (11 of 16 at depth 4), never all of them; the autograd graph
(``tree_torch.forest_forward_reference``) computes every leaf and differentiates them all.

With the cotangent q [N, B, A] of ``mix`` and phi = sum_b q_b . mix_b:

* ``tree_st_vjp``: grad phi in (w, b, K, beta), the backward;
* ``tree_st_hvp``: for a direction V = (Vw, Vb, VK, Vbeta) of the same shapes, the two
  halves of the double backward (TALO's Hessian-vector product): d(grad phi . V)/dq =
  the forward derivative of ``mix`` along V (per sample), and d(grad phi . V)/d theta =
  Hess(phi) V (phi is a sum of smooth pieces on a fixed route, so the Hessian is
  symmetric there).

tests/test_tree_grad_kernels.py checks values, routes, gradients and HVPs against
autograd on the reference graph (to ~1e-15 relative with float64 parameters). Dot products
may be summed in any order (vectorized), so margins agree with the reference's and the
actors' to rounding, as the reference's agree with the actors'. One core, no threads,
``nogil``: the learner thread leaves the interpreter lock to the actor's while it runs.
"""
from __future__ import annotations

import math

import numpy as np
from numba import njit

_FAST = {"reassoc", "contract"}   # lets LLVM vectorize the feature-axis dot products


@njit(cache=True, inline="always", fastmath=_FAST)
def _dot(x, y):
    s = 0.0
    for o in range(x.shape[0]):
        s += x[o] * y[o]
    return s


@njit(cache=True, inline="always")
def _sigmoid(x):
    if x >= 0.0:
        return 1.0 / (1.0 + math.exp(-x))
    e = math.exp(x)
    return e / (1.0 + e)


@njit(cache=True, inline="always")
def _tanh(x):
    """tanh from one expm1 (a third of libm's tanh here; relative error ~1e-16): for the
    leaves off the route, which only derivatives read. The routed leaf's value uses
    math.tanh, the actors' function."""
    e = math.expm1(-2.0 * abs(x))
    t = -e / (2.0 + e)
    return t if x >= 0.0 else -t


@njit(cache=True, inline="always")
def _hard_leaf(node, right, n_internal):
    """The leaf reached from heap node ``node`` by hard routing (``right`` [I] bool)."""
    while node < n_internal:
        node = 2 * node + 1 + (1 if right[node] else 0)
    return node - n_internal


@njit(cache=True, nogil=True, fastmath=_FAST)
def tree_st_forward(w, b, K, beta, obs, depth, tau, near):
    """mix [N,B,A] (= tanh(u) at the hard leaf), margins [N,B,I], leaf [N,B], nodes and
    sides [N,B,D] (sides True = right) for obs [N,B,O]. With ``near`` also what the
    backward reads (else empty arrays): the leaves one mismatch away, ``sib`` [N,B,D]
    (leaving the route at level j), tanh(u) of the hard leaf and of those, ``t_near``
    [N,B,D+1,A], and sigmoid'(m/tau)/tau on the route, ``g1`` [N,B,D]."""
    N, B, O = obs.shape
    n_internal, A = w.shape[1], K.shape[2]
    mix = np.empty((N, B, A))
    margins = np.empty((N, B, n_internal))
    leaf = np.empty((N, B), dtype=np.int64)
    nodes = np.empty((N, B, depth), dtype=np.int64)
    sides = np.empty((N, B, depth), dtype=np.bool_)
    M = B if near else 0
    sib = np.empty((N, M, depth), dtype=np.int64)
    t_near = np.empty((N, M, depth + 1, A))
    g1 = np.empty((N, M, depth))
    right = np.empty(n_internal, dtype=np.bool_)
    for n in range(N):
        for s in range(B):
            o = obs[n, s]
            for k in range(n_internal):
                margins[n, s, k] = _dot(o, w[n, k]) - b[n, k]
                right[k] = margins[n, s, k] > 0.0       # Eq. (hard_gate)
            node = 0
            for level in range(depth):
                nodes[n, s, level] = node
                sides[n, s, level] = right[node]
                node = 2 * node + 1 + (1 if right[node] else 0)
            lf = node - n_internal
            leaf[n, s] = lf
            for a in range(A):
                mix[n, s, a] = math.tanh(_dot(K[n, lf, a], o) + beta[n, lf, a])
            if not near:
                continue
            for a in range(A):
                t_near[n, s, 0, a] = mix[n, s, a]
            for level in range(depth):
                k = nodes[n, s, level]
                other = _hard_leaf(2 * k + 1 + (0 if right[k] else 1), right, n_internal)
                sib[n, s, level] = other
                for a in range(A):
                    t_near[n, s, level + 1, a] = _tanh(_dot(K[n, other, a], o) + beta[n, other, a])
                p = _sigmoid(margins[n, s, k] / tau)
                g1[n, s, level] = p * (1.0 - p) / tau
    return mix, margins, leaf, nodes, sides, sib, t_near, g1


@njit(cache=True, nogil=True, fastmath=_FAST)
def tree_st_vjp(q, obs, leaf, nodes, sides, t_near, g1, shape_w, shape_K):
    """grad of sum_b q_b . mix_b in (w, b, K, beta), from the forward's ``near`` arrays.
    The margin of route node k_j gets sigmoid'(m/tau)/tau (t_{l*} - t_{sib_j}) . q with the
    sign of the hard side (sib_j: the leaf reached by leaving the route at k_j); the hard
    leaf's gains get q (1 - t^2) o."""
    N, B, O = obs.shape
    n_internal, L, A = shape_w[1], shape_K[1], shape_K[2]
    depth = nodes.shape[2]
    gw = np.zeros((N, n_internal, O))
    gb = np.zeros((N, n_internal))
    gK = np.zeros((N, L, A, O))
    gbeta = np.zeros((N, L, A))
    for n in range(N):
        for s in range(B):
            o = obs[n, s]
            lf = leaf[n, s]
            q_t_star = 0.0
            for a in range(A):
                t = t_near[n, s, 0, a]
                q_t_star += q[n, s, a] * t
                r = q[n, s, a] * (1.0 - t * t)
                gbeta[n, lf, a] += r
                for f in range(O):
                    gK[n, lf, a, f] += r * o[f]
            for level in range(depth):
                k = nodes[n, s, level]
                q_t_sib = 0.0
                for a in range(A):
                    q_t_sib += q[n, s, a] * t_near[n, s, level + 1, a]
                mu = g1[n, s, level] * (q_t_star - q_t_sib)
                if not sides[n, s, level]:
                    mu = -mu
                gb[n, k] -= mu
                for f in range(O):
                    gw[n, k, f] += mu * o[f]
    return gw, gb, gK, gbeta


@njit(cache=True, inline="always")
def _leaf_off_route(right, m1, m2, depth, g1, g2, path, f1, f2):
    """Walk from the root by the hard decisions, leaving them at levels ``m1`` and ``m2``
    (-1: not at all): fills the path's nodes and its signed sigmoid'/sigmoid'' factors
    and returns the leaf reached."""
    node = 0
    for level in range(depth):
        go_right = right[node] != (level == m1 or level == m2)
        path[level] = node
        sign = 1.0 if go_right else -1.0
        f1[level] = sign * g1[node]
        f2[level] = sign * g2[node]
        node = 2 * node + 1 + (1 if go_right else 0)
    return node - right.shape[0]


@njit(cache=True, nogil=True, fastmath=_FAST)
def tree_st_hvp(q, Vw, Vb, VK, Vbeta, K, beta, obs, margins, t_near, tau, depth):
    """Both halves of the double backward along V = (Vw, Vb, VK, Vbeta): the forward
    derivative of mix [N,B,A] and Hess(sum_b q_b . mix_b) V in (w, b, K, beta).

    Per sample only the leaves at most two mismatches off the hard route have second
    derivatives: the hard leaf, the D leaves that leave the route once (at level m) and
    the D(D-1)/2 that leave it twice (m1 < m2). Their weights' derivatives in the route's
    margins are products of the path's sigmoid' factors f1 (sigmoid'' f2 on the diagonal)
    with every other factor at its hard value, which gives per level j, with
    S = sum_j f1_j dm_j along the leaf's path:
      no mismatch:  d weight / dm_j = f1_j,   d^2 weight . dm |_j = f2_j dm_j + f1_j (S - f1_j dm_j)
      one, at m:    d weight / dm_m = f1_m;   |_m = f2_m dm_m + f1_m (S - f1_m dm_m), |_j = f1_j f1_m dm_m
      two, m1, m2:  first derivatives 0;      |_m1 = f1_m1 f1_m2 dm_m2, |_m2 = f1_m2 f1_m1 dm_m1."""
    N, B, O = obs.shape
    n_internal, L, A = Vw.shape[1], K.shape[1], K.shape[2]
    dmix = np.zeros((N, B, A))
    hw = np.zeros(Vw.shape)
    hb = np.zeros(Vb.shape)
    hK = np.zeros(K.shape)
    hbeta = np.zeros(beta.shape)
    right = np.empty(n_internal, dtype=np.bool_)
    dm = np.empty(n_internal)          # directional derivative of each margin along V
    g1 = np.empty(n_internal)          # sigmoid'(m/tau)/tau
    g2 = np.empty(n_internal)          # sigmoid''(m/tau)/tau^2
    nu = np.zeros(n_internal)          # this sample's cotangent of each margin
    path = np.empty(depth, dtype=np.int64)
    f1 = np.empty(depth)               # d(factor)/dm along the leaf's path (signed)
    f2 = np.empty(depth)
    dw1 = np.empty(depth)              # d weight_l / d m_{path_j}
    second = np.empty(depth)           # (d^2 weight_l . dm)_j
    t = np.empty(A)
    du = np.empty(A)
    # the leaves with second derivatives, as the levels (m1, m2) where they leave the route
    n_cases = 1 + depth + depth * (depth - 1) // 2
    misses = np.full((n_cases, 2), -1, dtype=np.int64)
    for m1 in range(depth):
        misses[1 + m1, 0] = m1
    c = 1 + depth
    for m1 in range(depth):
        for m2 in range(m1 + 1, depth):
            misses[c, 0], misses[c, 1] = m1, m2
            c += 1
    for n in range(N):
        for s in range(B):
            o = obs[n, s]
            for k in range(n_internal):
                m = margins[n, s, k]
                right[k] = m > 0.0
                p = _sigmoid(m / tau)
                g1[k] = p * (1.0 - p) / tau
                g2[k] = p * (1.0 - p) * (1.0 - 2.0 * p) / (tau * tau)
                dm[k] = _dot(Vw[n, k], o) - Vb[n, k]
                nu[k] = 0.0
            for case in range(n_cases):
                m1, m2 = misses[case, 0], misses[case, 1]
                lf = _leaf_off_route(right, m1, m2, depth, g1, g2, path, f1, f2)
                S = 0.0                                      # sum_j f1_j dm_j (two mismatches: unused)
                if m2 < 0:
                    for j in range(depth):
                        S += f1[j] * dm[path[j]]
                if m1 < 0:                                   # the hard leaf
                    for j in range(depth):
                        dw1[j] = f1[j]
                        second[j] = f2[j] * dm[path[j]] + f1[j] * (S - f1[j] * dm[path[j]])
                    s_l, weight, near = S, 1.0, 0
                elif m2 < 0:                                 # one mismatch, at m1
                    fm, dmm = f1[m1], dm[path[m1]]
                    for j in range(depth):
                        dw1[j] = 0.0
                        second[j] = f1[j] * fm * dmm
                    dw1[m1] = fm
                    second[m1] = f2[m1] * dmm + fm * (S - fm * dmm)
                    s_l, weight, near = fm * dmm, 0.0, m1 + 1
                else:                                        # two mismatches
                    for j in range(depth):
                        dw1[j] = 0.0
                        second[j] = 0.0
                    second[m1] = f1[m1] * f1[m2] * dm[path[m2]]
                    second[m2] = f1[m2] * f1[m1] * dm[path[m1]]
                    s_l, weight, near = 0.0, 0.0, -1
                q_t, q_du = 0.0, 0.0           # q . t_l,  q . (1 - t_l^2) dU_l
                for a in range(A):
                    t[a] = t_near[n, s, near, a] if near >= 0 else _tanh(_dot(K[n, lf, a], o) + beta[n, lf, a])
                    du[a] = _dot(VK[n, lf, a], o) + Vbeta[n, lf, a]
                    q_t += q[n, s, a] * t[a]
                    q_du += q[n, s, a] * (1.0 - t[a] * t[a]) * du[a]
                    dmix[n, s, a] += s_l * t[a] + weight * (1.0 - t[a] * t[a]) * du[a]
                # margins: (d^2 weight . dm) (q . t) + d weight (q . (1-t^2) dU)
                for j in range(depth):
                    nu[path[j]] += second[j] * q_t + dw1[j] * q_du
                if m2 < 0:
                    # gains: s_l q (1 - t^2) + weight q (-2 t (1 - t^2)) dU
                    for a in range(A):
                        d1 = 1.0 - t[a] * t[a]
                        rho = q[n, s, a] * (s_l * d1 - 2.0 * weight * t[a] * d1 * du[a])
                        if rho != 0.0:
                            hbeta[n, lf, a] += rho
                            for f in range(O):
                                hK[n, lf, a, f] += rho * o[f]
            for k in range(n_internal):
                if nu[k] != 0.0:
                    hb[n, k] -= nu[k]
                    for f in range(O):
                        hw[n, k, f] += nu[k] * o[f]
    return dmix, hw, hb, hK, hbeta
