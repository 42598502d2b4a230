"""The actor's check of a shield answer against the rows it sent itself.

An actor executes an answer only if it verifies (fail closed otherwise), so a
forged, stale or buggy shield is harmless even on an open network:

* shape and finiteness of ``a_exec``;
* the action box ``[-1, 1]`` (within ``tol``);
* the fixed (human) block untouched: ``a_exec == a_prop`` there, bit for bit;
* ``status`` is OPTIMAL or INFEASIBLE; MAX_ITER answers are not certified
  (common/shield/qp.py) and are refused;
* OPTIMAL answers satisfy every masked row, ``c_i - C_i a_exec <= tol * max(1, ||C_i||)``;
* INFEASIBLE answers (the slack QP's minimum-violation action) must be
  genuinely infeasible: the actor re-solves just those problems locally with
  the same exact QP and refuses the answer if it finds a feasible point, or if
  the answer violates a row by more than the local minimum violation + ``tol``.
  Infeasible row sets are rare, so the local solve costs little;
* OPTIMAL answers are the projection, not merely a feasible point: the KKT
  conditions of Eq. (qpshield) hold to ``tol``, a_exec - a_prop = C_A^T lambda
  + box multipliers with lambda >= 0 on the rows and box faces active at
  a_exec, and complementary slackness. The multipliers are the actor's own:
  a small NNLS on the active rows (``qp_solver.diagnostics_batch``, the same
  certificate the QP reports), independent of anything the shield sends. The
  projection is strictly convex, so its KKT point is unique: a feasible but
  wrong answer ("all zeros, optimal") is refused as ``kkt``.

``verify_answer`` returns ``None`` for an answer to execute, else the reason
(one of ``REJECT_REASONS``) it was refused: the first failed check in the
order above, over the whole batch. The checks run as one compiled pass
(``row_kernels.check_answer_kernel``); ``verify_answer_fallback`` is the
same in numpy, check by check: the path for a status array that is not of an
integer type (not what a shield sends), and the kernel's oracle in the tests.
"""
from __future__ import annotations

import numpy as np

from common.safety_rows import SafetyRows
from common.shield.qp_solver import STATUS_INFEASIBLE, STATUS_OPTIMAL, diagnostics_batch
from common.shield.qp import QPConfig, shield_actions
from common.shield.row_kernels import CHECK_ORDER, check_answer_kernel

REJECT_REASONS = ("shape", "nonfinite", "box", "fixed_block", "status", "rows", "infeasible_claim", "kkt")
_QP = QPConfig()


def verify_answer(a_prop: np.ndarray, rows: SafetyRows, a_exec: np.ndarray, status: np.ndarray,
                  tol: float = 1e-6, backend: str = "default") -> str | None:
    a_prop = np.asarray(a_prop, dtype=np.float64)
    a_exec = np.asarray(a_exec)
    status = np.asarray(status)
    if a_exec.shape != a_prop.shape or status.shape != a_prop.shape[:1]:
        return "shape"
    if a_exec.dtype.kind != "f":
        return "nonfinite"
    if status.dtype.kind not in "iu":   # not what a shield sends: checked the slow way, same verdict
        return verify_answer_fallback(a_prop, rows, a_exec, status, tol, backend)
    C, c = np.asarray(rows.C, np.float64), np.asarray(rows.c, np.float64)
    if C.shape[:1] + C.shape[2:] != a_prop.shape or c.shape != C.shape[:2]:
        return "shape"
    fixed = np.broadcast_to(np.asarray(rows.fixed_mask, dtype=bool), a_prop.shape)
    mask = np.broadcast_to(np.asarray(rows.row_mask, dtype=bool), c.shape)
    failed, violation = check_answer_kernel(
        np.require(a_prop, np.float64, "CA"), np.require(a_exec, np.float64, "CA"),
        np.require(status, np.int64, "CA"), np.require(C, np.float64, "CA"), np.require(c, np.float64, "CA"),
        np.require(mask, np.bool_, "CA"), np.require(fixed, np.bool_, "CA"),
        float(tol), STATUS_OPTIMAL, STATUS_INFEASIBLE)
    for reason, bad in zip(CHECK_ORDER, failed):
        if bad:
            return reason
    return (_check_infeasible_claims(a_prop, rows, status, violation, tol, backend)
            or _check_optimality(a_prop, rows, a_exec, status, tol))


def _check_optimality(a_prop, rows: SafetyRows, a_exec, status, tol) -> str | None:
    """Answers claimed OPTIMAL: the KKT residual of Eq. (qpshield) at a_exec
    (stationarity with NNLS multipliers on the active rows and box faces,
    primal feasibility, complementarity) is at most ``tol``."""
    optimal = np.flatnonzero(status == STATUS_OPTIMAL)
    if optimal.size == 0:
        return None
    a = np.require(np.asarray(a_prop, np.float64)[optimal], np.float64, "CA")
    x = np.require(np.asarray(a_exec, np.float64)[optimal], np.float64, "CA")
    C = np.require(np.asarray(rows.C, np.float64)[optimal], np.float64, "CA")
    c = np.require(np.asarray(rows.c, np.float64)[optimal], np.float64, "CA")
    mask = np.require(np.broadcast_to(np.asarray(rows.row_mask, bool), np.shape(rows.c))[optimal], np.bool_, "CA")
    fixed = np.require(np.broadcast_to(np.asarray(rows.fixed_mask, bool), np.shape(a_prop))[optimal], np.bool_, "CA")
    n, M = C.shape[:2]
    lo, hi = np.full(a.shape, -1.0), np.full(a.shape, 1.0)
    kkt = np.empty(n)
    diagnostics_batch(a, x, C, c, mask, fixed, lo, hi, np.full(n, STATUS_OPTIMAL, np.int64), _QP.slack_rho,
                      _QP.active_tol, np.empty((n, M), np.bool_), np.empty(n), kkt, np.empty(n))
    return "kkt" if not np.all(kkt <= tol) else None


def _check_infeasible_claims(a_prop, rows: SafetyRows, status, violation, tol, backend) -> str | None:
    """Problems claimed infeasible: re-solved locally with the same exact QP."""
    claimed = status == STATUS_INFEASIBLE
    if claimed.any():
        idx = np.flatnonzero(claimed)
        local = shield_actions(a_prop[idx], rows.select(idx), backend=backend)
        if np.any(local.status != STATUS_INFEASIBLE):
            return "infeasible_claim"
        local_violation = rows.select(idx).scaled_violation(local.a_exec)
        if np.any(violation[idx] > local_violation + tol):
            return "rows"
    return None


def verify_answer_fallback(a_prop: np.ndarray, rows: SafetyRows, a_exec: np.ndarray, status: np.ndarray,
                           tol: float = 1e-6, backend: str = "default") -> str | None:
    """``verify_answer`` in numpy, check by check: its path for a status array that is not
    of an integer type (the kernel takes int64), and the kernel's oracle in the tests."""
    a_prop = np.asarray(a_prop, dtype=np.float64)
    a_exec = np.asarray(a_exec)
    status = np.asarray(status)
    if a_exec.shape != a_prop.shape or status.shape != a_prop.shape[:1]:
        return "shape"
    if a_exec.dtype.kind != "f" or not np.isfinite(a_exec).all():
        return "nonfinite"
    a_exec = a_exec.astype(np.float64, copy=False)
    if np.abs(a_exec).max(initial=0.0) > 1.0 + tol:
        return "box"
    fixed = np.broadcast_to(np.asarray(rows.fixed_mask, dtype=bool), a_prop.shape)
    if not np.array_equal(a_exec[fixed], a_prop[fixed]):
        return "fixed_block"
    if not np.isin(status, (STATUS_OPTIMAL, STATUS_INFEASIBLE)).all():
        return "status"
    violation = rows.scaled_violation(a_exec)
    claimed = status == STATUS_INFEASIBLE
    if np.any(violation[~claimed] > tol):
        return "rows"
    return (_check_infeasible_claims(a_prop, rows, status, violation, tol, backend)
            or _check_optimality(a_prop, rows, a_exec, status, tol))
