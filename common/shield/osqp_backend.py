"""OSQP backend for the joint CBF-QP shield (Eq. qpshield).

One OSQP problem is set up per batch with a dense, fixed sparsity pattern
(rows = M safety rows + d box rows) and then updated per QP (q, l, u and the
A values), so OSQP reuses its workspace and warm-starts. Fixed variables are
substituted exactly as in the active-set backend: their columns are zeroed in
the rows (c ← c − C_F a_F) and their box row is pinned to l = u = a_k.
Tight tolerances plus solution polishing make it agree with the exact
active-set answer to ~1e-7.

Infeasible row sets: OSQP's primal-infeasibility certificate (or a constant
row violated by the fixed block) triggers the fail-closed slack QP of
common/shield/qp.py. OSQP itself does not converge on that QP (ρ = 1e6 makes the
multipliers ~1e5; it hits max_iter far from the answer), so those problems are
handed to the active-set kernel, which solves the same lifted slack QP exactly.
"""
from __future__ import annotations

import numpy as np
import osqp
import scipy.sparse as sp

from common.shield.qp_solver import STATUS_MAX_ITER, STATUS_OPTIMAL, solve_batch_active_set

_SOLVED = int(osqp.SolverStatus.OSQP_SOLVED)
_INFEASIBLE = (int(osqp.SolverStatus.OSQP_PRIMAL_INFEASIBLE),
               int(osqp.SolverStatus.OSQP_PRIMAL_INFEASIBLE_INACCURATE))


def _settings(cfg) -> dict:
    return dict(
        verbose=False,
        eps_abs=cfg.osqp_eps,
        eps_rel=cfg.osqp_eps,
        eps_prim_inf=cfg.osqp_eps_infeasible,
        eps_dual_inf=cfg.osqp_eps_infeasible,
        polishing=True,
        polish_refine_iter=10,
        max_iter=cfg.osqp_max_iter,
        warm_starting=True,
        # OSQP's default (0) times the factorization to decide when to adapt its
        # step size: non-deterministic, and at eps = 1e-9 it can stall to max_iter.
        adaptive_rho_interval=25,
    )


def solve_batch_osqp(a, C, c, row_mask, fixed, lo, hi, cfg):
    """Loop of per-problem OSQP solves over an updated problem (see module doc)."""
    B, M, d = C.shape
    x_out = a.copy()
    status = np.zeros(B, dtype=np.int64)
    iters = np.zeros(B, dtype=np.int64)
    # Dense pattern: every entry of the M×d row block, then the d×d identity.
    pattern = sp.csc_matrix(np.vstack([np.ones((M, d)), np.eye(d)]))
    ri, ci = pattern.nonzero()
    order = np.lexsort((ri, ci))  # CSC data order: column-major, rows ascending
    ri, ci = ri[order], ci[order]
    on_rows = ri < M
    prob = None
    infeasible = []
    for b in range(B):
        free = ~fixed[b]
        cb = c[b] - C[b][:, ~free] @ a[b, ~free]
        Cb = np.where(free[None, :], C[b], 0.0)
        Cb = np.where(row_mask[b][:, None], Cb, 0.0)
        l = np.concatenate([np.where(row_mask[b], cb, -np.inf), np.where(free, lo[b], a[b])])
        u = np.concatenate([np.full(M, np.inf), np.where(free, hi[b], a[b])])
        Ax = np.ones(len(ri))
        Ax[on_rows] = Cb[ri[on_rows], ci[on_rows]]
        if prob is None:
            A = sp.csc_matrix((Ax, (ri, ci)), shape=(M + d, d))
            prob = osqp.OSQP()
            prob.setup(sp.eye(d, format="csc"), -a[b], A, l, u, **_settings(cfg))
        else:
            prob.update(q=-a[b], l=l, u=u, Ax=Ax)
        res = prob.solve(raise_error=False)
        iters[b] = res.info.iter
        if res.info.status_val != _SOLVED and res.info.status_val not in _INFEASIBLE:
            # Rare stalls of the updated problem (scaling and warm start come from
            # other QPs): retry once with a fresh setup of this QP alone.
            fresh = osqp.OSQP()
            fresh.setup(sp.eye(d, format="csc"), -a[b], sp.csc_matrix((Ax, (ri, ci)), shape=(M + d, d)),
                        l, u, **_settings(cfg))
            res = fresh.solve(raise_error=False)
            iters[b] += res.info.iter
        row_norm = np.linalg.norm(Cb, axis=1)
        constant_violated = np.any(row_mask[b] & (row_norm <= cfg.zero_tol) & (cb > cfg.tol))
        if res.info.status_val == _SOLVED and not constant_violated:
            xb = res.x
            status[b] = STATUS_OPTIMAL
        elif res.info.status_val in _INFEASIBLE or constant_violated:
            infeasible.append(b)
            continue
        else:
            xb = res.x
            status[b] = STATUS_MAX_ITER
        # Fixed variables keep a_prop exactly; the box is always respected.
        x_out[b, free] = np.clip(xb[free], lo[b, free], hi[b, free])
    if infeasible:
        idx = np.array(infeasible)
        xs, st, it = x_out[idx], status[idx], np.zeros(len(idx), dtype=np.int64)
        solve_batch_active_set(a[idx], C[idx], c[idx], row_mask[idx], fixed[idx], lo[idx], hi[idx],
                               cfg.tol, cfg.dep_tol, cfg.zero_tol, cfg.max_iter, cfg.slack_rho,
                               xs, st, it)
        x_out[idx], status[idx], iters[idx] = xs, st, iters[idx] + it
    return x_out, status, iters

