"""Exact joint CBF-QP shield, Eq. (qpshield), batched.

For every problem b of a batch

    a_exec = argmin_ã ½‖ã − a_prop‖²   s.t.  C ã ≥ c  (rows with row_mask),
                                             lo ≤ ã ≤ hi  (free variables only),
                                             ã_k = a_prop_k  for fixed k (fixed_mask).

Fixed variables (a human partner's measured block, Sec. III-B) are substituted
into the rows, c ← c − C_F a_F, and only the free variables are optimized; they
come back bit-identical to a_prop.

Infeasible row sets fail closed. When the rows and the box admit no point, the
answer is the minimizer of the slack QP

    min_{ã, s} ½‖ã − a_prop‖² + ρ/2 ‖s‖²   s.t.  C ã + s ≥ c,  s ≥ 0,  lo ≤ ã ≤ hi,

(ρ = QPConfig.slack_rho, default 1e6; equivalently min ½‖ã − a‖² + ρ/2 Σ_i [c_i − C_i ã]_+²
over the box), flagged STATUS_INFEASIBLE, with ``slack`` = max_i s_i, the
largest remaining row violation. As ρ → ∞ this tends to the lexicographic answer
(least-squares violation first, then distance); the box is always respected.

Backends: ``"dual_active_set"`` (Goldfarb–Idnani, numba, default) and
``"osqp"`` (per-problem OSQP with updates, tight tolerances, polishing; it
detects infeasible sets itself but hands their slack QP to the active-set
kernel, on which OSQP does not converge). STATUS_MAX_ITER marks an answer that
is not certified (never seen on the benchmark families); callers must treat it
as unsafe.
Diagnostics (active rows, KKT residual, slack) are computed afterwards from the
returned primal by one shared kernel, independently of the backend.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from common.safety_rows import SafetyRows
from common.shield.qp_solver import (
    STATUS_INFEASIBLE,
    STATUS_MAX_ITER,
    STATUS_OPTIMAL,
    diagnostics_batch,
    solve_batch_active_set,
)

__all__ = [
    "STATUS_OPTIMAL", "STATUS_INFEASIBLE", "STATUS_MAX_ITER", "QPConfig", "QPResult",
    "InvalidQPInput", "solve_cbf_qp", "shield_actions", "qp_violation", "BACKENDS", "DEFAULT_BACKEND",
]


@dataclass(frozen=True)
class QPConfig:
    """Tolerances of the shield. One source of defaults for every backend."""

    tol: float = 1e-10            # row counts as violated below −tol·max(1, ‖C_i‖)
    dep_tol: float = 1e-12        # row p is dependent on the active rows if ‖z‖ ≤ dep_tol‖C_p‖
    zero_tol: float = 1e-14       # a row whose free part has norm ≤ zero_tol is a constant row
    max_iter: int = 1000          # active-set steps per problem (adds + drops)
    slack_rho: float = 1e6        # ρ of the infeasible-set slack QP (module docstring)
    active_tol: float = 1e-7      # |C_i x − c_i| ≤ active_tol·max(1, ‖C_i‖) counts as active
    osqp_eps: float = 1e-9        # OSQP eps_abs = eps_rel
    osqp_eps_infeasible: float = 1e-9
    osqp_max_iter: int = 200_000


@dataclass
class QPResult:
    """Executed actions and per-problem diagnostics (see docs/interfaces.md)."""

    a_exec: np.ndarray            # [B, d]
    status: np.ndarray            # [B] int: STATUS_OPTIMAL / STATUS_INFEASIBLE / STATUS_MAX_ITER
    active: np.ndarray            # [B, M] bool: masked rows with C_i a_exec ≤ c_i + tol
    correction_norm: np.ndarray   # [B] ‖a_exec − a_prop‖
    kkt_residual: np.ndarray      # [B] max(stationarity, primal inf., dual inf., complementarity)
    slack: np.ndarray             # [B] max row violation for STATUS_INFEASIBLE, 0 otherwise
    iterations: np.ndarray        # [B] solver iterations


class InvalidQPInput(ValueError):
    """NaN/Inf or shape errors in the inputs of solve_cbf_qp."""


def _active_set_backend(a, C, c, row_mask, fixed, lo, hi, cfg):
    B, M, d = C.shape
    x = np.empty((B, d))
    status = np.empty(B, dtype=np.int64)
    iters = np.empty(B, dtype=np.int64)
    solve_batch_active_set(a, C, c, row_mask, fixed, lo, hi, cfg.tol, cfg.dep_tol, cfg.zero_tol,
                           cfg.max_iter, cfg.slack_rho, x, status, iters)
    return x, status, iters


def _osqp_backend(a, C, c, row_mask, fixed, lo, hi, cfg):
    from common.shield.osqp_backend import solve_batch_osqp  # osqp/scipy load only when asked for

    return solve_batch_osqp(a, C, c, row_mask, fixed, lo, hi, cfg)


# name -> callable(a, C, c, row_mask, fixed, lo, hi, cfg) -> (a_exec, status, iterations)
BACKENDS = {
    "dual_active_set": _active_set_backend,
    "osqp": _osqp_backend,
}
DEFAULT_BACKEND = "dual_active_set"


def _finite(name: str, arr: np.ndarray) -> None:
    bad = ~np.isfinite(arr)
    if bad.any():
        where = np.argwhere(bad)[0]
        kind = "NaN" if np.isnan(arr[tuple(where)]) else "Inf"
        raise InvalidQPInput(
            f"{name} contains {kind} at index {tuple(int(i) for i in where)} "
            f"(problem {int(where[0])} of the batch)"
        )


def _as_float(name: str, value, ndim: int) -> np.ndarray:
    try:
        arr = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise InvalidQPInput(f"{name} must be numeric: {exc}") from None
    if arr.ndim != ndim:
        raise InvalidQPInput(f"{name} must have {ndim} dims, got shape {arr.shape}")
    return arr


def _validate(a_prop, C, c, row_mask, fixed_mask, lo, hi):
    a = _as_float("a_prop", a_prop, 2)
    C = _as_float("C", C, 3)
    c = _as_float("c", c, 2)
    B, d = a.shape
    if C.shape[0] != B or C.shape[2] != d:
        raise InvalidQPInput(f"C must be [B={B}, M, d={d}], got {C.shape}")
    M = C.shape[1]
    if c.shape != (B, M):
        raise InvalidQPInput(f"c must be [B, M] = {(B, M)}, got {c.shape}")
    if row_mask is None:
        mask = np.ones((B, M), dtype=bool)
    else:
        mask = np.asarray(row_mask)
        if mask.shape != (B, M):
            raise InvalidQPInput(f"row_mask must be [B, M] = {(B, M)}, got {mask.shape}")
        mask = mask.astype(bool)
    if fixed_mask is None:
        fixed = np.zeros((B, d), dtype=bool)
    else:
        fixed = np.asarray(fixed_mask)
        if fixed.shape == (d,):
            fixed = np.broadcast_to(fixed, (B, d))
        if fixed.shape != (B, d):
            raise InvalidQPInput(f"fixed_mask must be [B, d] or [d] with d={d}, got {fixed.shape}")
        fixed = fixed.astype(bool)
    bounds = []
    for name, v in (("lo", lo), ("hi", hi)):
        arr = np.asarray(v, dtype=np.float64)
        try:
            arr = np.broadcast_to(arr, (B, d))
        except ValueError:
            raise InvalidQPInput(f"{name} must be a scalar, [d] or [B, d] with d={d}, got {arr.shape}") from None
        bounds.append(arr)
    lo_b, hi_b = bounds
    for name, arr in (("a_prop", a), ("C", C), ("c", c), ("lo", lo_b), ("hi", hi_b)):
        _finite(name, arr)
    if (lo_b > hi_b).any():
        where = np.argwhere(lo_b > hi_b)[0]
        raise InvalidQPInput(f"lo > hi at index {tuple(int(i) for i in where)} (problem {int(where[0])})")
    return (np.ascontiguousarray(a), np.ascontiguousarray(C), np.ascontiguousarray(c),
            np.ascontiguousarray(mask), np.ascontiguousarray(fixed),
            np.ascontiguousarray(lo_b), np.ascontiguousarray(hi_b))


def solve_cbf_qp(a_prop, C, c, row_mask=None, fixed_mask=None, lo=-1.0, hi=1.0,
                 backend: str = "default", config: QPConfig | None = None) -> QPResult:
    """Batched exact projection Eq. (qpshield) onto {C ã ≥ c} ∩ box, fixed block held.

    a_prop [B,d], C [B,M,d], c [B,M], row_mask [B,M] (None: all rows),
    fixed_mask [B,d] or [d] (None: nothing fixed), lo/hi scalar, [d] or [B,d].
    Raises InvalidQPInput on NaN/Inf (naming the argument and problem index) or bad shapes.
    """
    cfg = config or QPConfig()
    name = DEFAULT_BACKEND if backend == "default" else backend
    if name not in BACKENDS:
        raise ValueError(f"unknown QP backend {backend!r}; choose from {sorted(BACKENDS)} or 'default'")
    a, C, c, mask, fixed, lo_b, hi_b = _validate(a_prop, C, c, row_mask, fixed_mask, lo, hi)
    B, M, d = C.shape
    x, status, iters = BACKENDS[name](a, C, c, mask, fixed, lo_b, hi_b, cfg)
    x[fixed] = a[fixed]  # exactly as measured, whatever the backend did
    active = np.zeros((B, M), dtype=bool)
    corr = np.empty(B)
    kkt = np.empty(B)
    slack = np.empty(B)
    diagnostics_batch(a, x, C, c, mask, fixed, lo_b, hi_b, status, cfg.slack_rho, cfg.active_tol,
                      active, corr, kkt, slack)
    return QPResult(a_exec=x, status=status, active=active, correction_norm=corr,
                    kkt_residual=kkt, slack=slack, iterations=iters)


def shield_actions(a_prop, rows: SafetyRows, backend: str = "default", config: QPConfig | None = None) -> QPResult:
    """Eq. (qpshield) on one step's ``SafetyRows``: the executed actions of B envs."""
    return solve_cbf_qp(a_prop, rows.C, rows.c, rows.row_mask, rows.fixed_mask, backend=backend, config=config)


def qp_violation(a, C, c, row_mask=None) -> np.ndarray:
    """Largest row violation max_i [c_i − C_i a]_+ over masked rows, per problem.

    Batched ([B,d], [B,M,d], [B,M]) -> [B]; unbatched ([d], [M,d], [M]) -> float.
    """
    a = np.asarray(a, dtype=np.float64)
    C = np.asarray(C, dtype=np.float64)
    c = np.asarray(c, dtype=np.float64)
    single = a.ndim == 1
    if single:
        a, C, c = a[None], C[None], c[None]
        row_mask = None if row_mask is None else np.asarray(row_mask)[None]
    if C.ndim != 3 or C.shape[0] != a.shape[0] or C.shape[2] != a.shape[1] or c.shape != C.shape[:2]:
        raise InvalidQPInput(f"qp_violation shapes disagree: a {a.shape}, C {C.shape}, c {c.shape}")
    viol = c - np.einsum("bmd,bd->bm", C, a)
    if row_mask is not None:
        viol = np.where(np.asarray(row_mask, dtype=bool), viol, -np.inf)
    out = np.maximum(viol.max(axis=1, initial=-np.inf), 0.0)
    return float(out[0]) if single else out
