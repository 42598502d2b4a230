"""TALO's gap (Eq. talo_gap) in closed form: g_ind, g_team, W_gap and grad W = J_d^T d
composed from the trees' and the surrogate chain's written-out derivatives, with no
autograd graph and no pass of autograd's engine.

The actors' parameters meet the surrogates only through the stacked tree actions
z = a_ST [B, D] (carrier i's block a function of theta_i alone) and log_std (common/algos/
talo.py, ``Through``). With the chain's cotangent sets (``ChainTape``) and the trees'
derivatives (``ForestTape``):

    d_i   = T_i^T q_i + s_i,  (q, s) = chain cotangents of L_i - L_team on carrier i's block
    g_team = T^T q_T + s_T,   (q_T, s_T) those of L_team
    W_gap = 1/2 ||d||^2
    grad W = J_d^T d = H_tree(q) V                  (the trees' curvature, q fixed)
                     + T^T h_a,  h_s                (the chain's: d's cotangents move with z, log_std)

with V = d, T = dz/dtheta (``ForestTape.vjp``), H_tree(q) V and the forward derivative
dz = T V from ``ForestTape.hvp``, and (h_a, h_s) the chain's Hessian along (dz, V_log_std),
each block's cotangent set seeing only its own block of the direction (``ChainTape.hvp``):
exactly the passes autograd's double backward runs on the ``Through`` graph, as four kernel
calls. d and g_team are rounded to the parameters' dtype, W_gap summed in it and the direction
d read back from it, as autograd does; autograd also rounds the cotangents at a_ST to the
action's dtype, which stay float64 here. So the two paths agree to 1e-10 with float64
parameters and to float32 rounding with float32 ones; tests/test_gap_closed_form.py checks them against
``talo.talo_gap`` on the graph (values, gradients, HVPs) for every method, in float64 and
float32, with human blocks, sparse trees and a lagged reference.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from common.algos.surrogate_chain import ChainTape
from common.policy.tree_torch import ForestTape

TREE_PARAMETERS = ("W", "b", "K", "beta", "log_std")   # each carrier's group, in order


@dataclass(frozen=True)
class Taped:
    """One forward of the proposal map without a graph: its trees' and its chain's tapes."""
    forest: ForestTape
    chain: ChainTape


def cotangent_sets(R: int, N: int, reference: int, which: str) -> np.ndarray:
    """Output cotangents [G, R, N+1] of the chain for reference policy ``reference``:
    "ind" (set j: L_j, on carrier j's block), "d" (set j: L_j - L_team) or "team" (L_team,
    one set for every block)."""
    if which not in ("ind", "d", "team"):
        raise ValueError(f"unknown cotangent set {which!r}")
    if which == "team":
        sets = np.zeros((1, R, N + 1))
        sets[0, reference, N] = 1.0
        return sets
    sets = np.zeros((N, R, N + 1))
    sets[np.arange(N), reference, np.arange(N)] = 1.0
    if which == "d":
        sets[:, reference, N] = -1.0
    return sets


class Layout:
    """The flat actor vector: carrier by carrier, W, b, K, beta, log_std (``TREE_PARAMETERS``)."""

    def __init__(self, groups):
        self.first = groups[0][0]          # read for the dtype at each call (a policy may be cast later)
        self.shapes = [tuple(p.shape) for p in groups[0]]
        self.sizes = [int(np.prod(s)) for s in self.shapes]
        self.N = len(groups)

    def flat(self, tree, s_bar: np.ndarray) -> Tensor:
        """(gW, gb, gK, gbeta) stacked [N, ...] and log_std's [N*A] -> the flat vector in the
        parameters' dtype (each entry rounded once, as autograd rounds a float32 parameter's
        float64 gradient)."""
        A = self.sizes[-1]
        pieces = []
        for i in range(self.N):
            pieces.extend(x[i].reshape(-1) for x in tree)
            pieces.append(s_bar[A * i:A * (i + 1)])
        return torch.from_numpy(np.concatenate(pieces)).to(self.first.dtype)

    def split(self, vec: Tensor):
        """The flat vector as float64 (V_W, V_b, V_K, V_beta) stacked [N, ...] and V_log_std [N*A]."""
        per = vec.detach().double().numpy().reshape(self.N, sum(self.sizes))
        cuts = np.cumsum(self.sizes)[:-1]
        blocks = np.split(per, cuts, axis=1)
        tree = [np.ascontiguousarray(blk).reshape(self.N, *shape) for blk, shape in zip(blocks[:4], self.shapes[:4])]
        return tree, np.ascontiguousarray(blocks[4]).reshape(-1)


def gradient(taped: Taped, sets: np.ndarray, layout: Layout) -> Tensor:
    """The flat gradient of the surrogates ``sets`` pick (``cotangent_sets``)."""
    a_bar, s_bar = taped.chain.vjp(sets)
    return layout.flat(taped.forest.vjp(a_bar), s_bar)


def talo_gap_closed_form(taped: Taped, reference: int, layout: Layout, with_hvp: bool):
    """``talo.talo_gap`` on the surrogates of reference ``reference``: (g_ind, g_team, W_gap,
    grad W or None), flat in the parameters' dtype."""
    R, N = taped.chain.sizes
    d_sets = cotangent_sets(R, N, reference, "d")
    q_d, s_d = taped.chain.vjp(d_sets)
    unit_d = taped.forest.unit_vjp(q_d)
    d = layout.flat(taped.forest.raw(unit_d), s_d)
    g_team = gradient(taped, cotangent_sets(R, N, reference, "team"), layout)
    w_gap = 0.5 * d.pow(2).sum()
    grad_w = None
    if with_hvp:
        V_tree, V_s = layout.split(d)
        dz, h_tree = taped.forest.hvp(q_d, V_tree, unit_d[0])          # H_tree(q) V and T V
        _, h_a, h_s = taped.chain.hvp(d_sets, dz, V_s)                   # the chain's Hessian along them
        through = taped.forest.vjp(h_a)                                  # T^T h_a
        grad_w = layout.flat([x + y for x, y in zip(h_tree, through)], h_s)
    return d + g_team, g_team, w_gap, grad_w
