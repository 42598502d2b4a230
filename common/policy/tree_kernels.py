"""Numba kernel of the team's hard-tree forward (Eq. hard_tree_policy), the
actor's per-step tree evaluation. Its numpy reference is
``common.policy.reference.team_forward``; tests/test_tree_kernel.py
compares them.

Per sample and carrier the kernel evaluates only the ``depth`` gates on the
routed path (the reference computes all ``2^depth - 1`` margins) and the one
reached leaf. A margin is the same dot product ``o . w_k - b_k`` as the
reference's, summed in feature order, so routes agree except where a margin is
zero to rounding. ``nogil``: in-process, the actor's forward runs beside the
learner's thread.
"""
from __future__ import annotations

import math

import numpy as np
from numba import njit


@njit(cache=True, nogil=True)
def team_forward_kernel(obs, w, b, K, beta, c_a, s_a, depth):
    """obs [B,N,O] f64; per carrier i: unit split vectors w [N,2^D-1,O], b [N,2^D-1],
    leaf gains K [N,2^D,A,O], beta [N,2^D,A], c_a, s_a [N,A].
    Returns a_tree [B,N*A], leaf [B,N], nodes [B,N,D], sides [B,N,D] (True = right)."""
    B, N, O = obs.shape
    A = c_a.shape[1]
    n_internal = w.shape[1]
    a_tree = np.empty((B, N * A))
    leaf = np.empty((B, N), dtype=np.int64)
    nodes = np.empty((B, N, depth), dtype=np.int64)
    sides = np.empty((B, N, depth), dtype=np.bool_)
    for s in range(B):
        for i in range(N):
            node = 0
            for level in range(depth):
                m = 0.0
                for o in range(O):
                    m += obs[s, i, o] * w[i, node, o]
                right = m - b[i, node] > 0.0          # Eq. (hard_gate)
                nodes[s, i, level] = node
                sides[s, i, level] = right
                node = 2 * node + 1 + (1 if right else 0)
            lf = node - n_internal
            leaf[s, i] = lf
            for a in range(A):
                u = 0.0
                for o in range(O):
                    u += K[i, lf, a, o] * obs[s, i, o]
                a_tree[s, i * A + a] = c_a[i, a] + s_a[i, a] * math.tanh(u + beta[i, lf, a])
    return a_tree, leaf, nodes, sides
