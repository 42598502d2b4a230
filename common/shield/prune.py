"""Dropping safety rows that the action box already implies (smaller shield requests).

A row ``C_j a >= c_j`` of problem ``b`` is *box-redundant* when every action of
that problem's feasible box satisfies it with room to spare:

    g_j = min_{lo <= a_free <= hi, a_F = a_prop_F} (C_j a - c_j)
        = C_jF a_prop_F + sum_{free k} min(C_jk lo_k, C_jk hi_k) - c_j  >  margin_j.

Such a row can never be active or violated at any point the shield may return
(every backend returns free variables inside the box, fixed ones equal to
``a_prop``), so removing it changes neither the feasible set ``{C a >= c} ∩ box``
nor the slack-QP objective ``½‖a − a_prop‖² + ρ/2 Σ [c_i − C_i a]_+²`` on the box
(its term is identically 0 there). Both QPs are strictly convex, so their unique
minimizers, and with them ``a_exec``, ``status`` and ``slack``, are the same with
or without the row: :func:`drop_box_redundant_rows` is exact, not a heuristic.
(Solver iterates may differ, so answers agree to rounding, ~1e-15, not bit for bit.)
"""
from __future__ import annotations

import inspect
import math

import numpy as np

from common.safety_rows import SafetyRows
from common.shield.qp import InvalidQPInput, QPConfig, solve_cbf_qp
from common.shield.row_kernels import compact_rows_kernel, keep_rows_kernel

__all__ = ["drop_box_redundant_rows", "kept_rows", "DEFAULT_LO", "DEFAULT_HI", "MARGIN_REL"]

# The box the shield solves over: the single source is solve_cbf_qp's own defaults
# (shield_actions and the shield service call it without lo/hi).
_SIG = inspect.signature(solve_cbf_qp).parameters
DEFAULT_LO: float = _SIG["lo"].default
DEFAULT_HI: float = _SIG["hi"].default

# A row is dropped only if its minimum over the box exceeds margin * max(1, ||C_j||),
# margin = max(MARGIN_REL, 10 * the QP's largest row tolerance). Why 1e-6: the QP and its
# diagnostics call a row violated below -tol (1e-10) and active within active_tol (1e-7),
# both relative to max(1, ||C_j,free||) <= max(1, ||C_j||). A margin 10x the largest of
# them keeps every dropped row outside the "active" band by a wide gap even at points
# slightly off the box (an OSQP iterate before its final clip; ||C_j|| * 1e-8 of excursion
# costs 1e-8 of the 9e-7 gap), so no backend or diagnostic can ever treat it as active or
# violated; and rows that touch the box exactly (minimum 0, e.g. at a corner) or nearly
# (minimum <= 1e-6) stay in the request. It equals the actor's own verification tolerance
# (verify.py, 1e-6): a dropped row holds by more than that at every box point.
MARGIN_REL = 1e-6
_GUARD = 4.0 * np.finfo(np.float64).eps   # floating-point guard on the computed minimum g_j (x2 spare)


def _arrays(a_prop, rows: SafetyRows):
    """float64 a [B, d], C [B, M, d], c [B, M]; bool row_mask [B, M], fixed_mask [B, d]."""
    a = np.asarray(a_prop, dtype=np.float64)
    C = np.asarray(rows.C, dtype=np.float64)
    c = np.asarray(rows.c, dtype=np.float64)
    if a.ndim != 2 or C.ndim != 3 or C.shape[0] != a.shape[0] or C.shape[2] != a.shape[1] or c.shape != C.shape[:2]:
        raise InvalidQPInput(f"drop_box_redundant_rows: shapes disagree: a_prop {a.shape}, C {C.shape}, c {c.shape}")
    mask = np.asarray(rows.row_mask, dtype=bool)
    fixed = np.asarray(rows.fixed_mask, dtype=bool)
    if mask.shape != c.shape:
        mask = np.broadcast_to(mask, c.shape)
    if fixed.shape != a.shape:
        fixed = np.broadcast_to(fixed, a.shape)
    return a, C, c, mask, fixed


def _margin(config: QPConfig | None) -> float:
    cfg = config or QPConfig()
    return max(MARGIN_REL, 10.0 * max(cfg.tol, cfg.active_tol))


def _scalar_box(lo, hi) -> tuple[float, float] | None:
    """(mid, half) of a scalar box (checked as solve_cbf_qp does), None for a per-column one."""
    if np.ndim(lo) != 0 or np.ndim(hi) != 0:
        return None
    lo_a, hi_a = float(lo), float(hi)
    if not (math.isfinite(lo_a) and math.isfinite(hi_a) and lo_a <= hi_a):
        raise InvalidQPInput(f"drop_box_redundant_rows: lo/hi must be finite with lo <= hi, got {lo}, {hi}")
    return 0.5 * (lo_a + hi_a), 0.5 * (hi_a - lo_a)


def _keep(a, C, c, mask, fixed, lo, hi, config) -> np.ndarray:
    """The kept-row mask: the compiled kernel for the usual scalar box (what
    every actor step asks), :func:`_keep_fallback` for a per-column box (which the
    kernel does not take)."""
    box = _scalar_box(lo, hi)
    if box is None:
        return _keep_fallback(a, C, c, mask, fixed, lo, hi, config)
    arrays = [np.require(v, dt, "CA") for v, dt in ((a, np.float64), (C, np.float64), (c, np.float64),
                                                     (mask, np.bool_), (fixed, np.bool_))]
    return keep_rows_kernel(*arrays, *box, _margin(config), _GUARD)


def _keep_fallback(a, C, c, mask, fixed, lo, hi, config) -> np.ndarray:
    """The kept-row mask in numpy, for any box: :func:`_keep`'s path for a per-column
    box (``keep_rows_kernel`` takes only a scalar one), and the kernel's oracle in the
    tests (through ``reference.drop_box_redundant_rows``)."""
    margin = _margin(config)
    B, M, d = C.shape
    box = _scalar_box(lo, hi)
    if box is not None:   # the usual scalar box: Python floats, fewer array ops
        mid, half = box
        half_max = half
    else:
        lo_a, hi_a = np.asarray(lo, dtype=np.float64), np.asarray(hi, dtype=np.float64)
        if not (np.isfinite(lo_a).all() and np.isfinite(hi_a).all()) or (lo_a > hi_a).any():
            raise InvalidQPInput("drop_box_redundant_rows: lo/hi must be finite with lo <= hi (as for solve_cbf_qp)")
        mid, half = 0.5 * (lo_a + hi_a), 0.5 * (hi_a - lo_a)
        half_max = float(half.max(initial=0.0))
    # min over [lo_k, hi_k] of C_jk a_k = C_jk mid_k - |C_jk| half_k; a fixed column
    # contributes C_jk a_prop_k (mid = a_prop, half = 0): two matrix-vector products.
    v = np.where(fixed, a, mid)
    w = np.where(fixed, 0.0, half)
    if v.shape != (B, d):
        raise InvalidQPInput(f"lo/hi must be a scalar, [d] or [B, d] with B={B}, d={d}")
    with np.errstate(invalid="ignore", over="ignore"):
        gap = (np.matmul(C, v[:, :, None]) - np.matmul(np.abs(C), w[:, :, None]))[..., 0] - c
        norm = np.sqrt(np.dot((C * C).reshape(B * M, d), np.ones(d)).reshape(B, M))
        # rounding: |fl(gap) - gap| <= (d + 2) u (sum_k |C_jk| (|v_k| + w_k) + |c_j|) (u = eps/2;
        # Higham's dot-product bound plus the mid/half split and the subtraction of c), and
        # sum_k |C_jk| (|v_k| + w_k) <= ||C_j|| sqrt(d) max_k (|v_k| + w_k): never drop on a
        # rounding artefact (NaN in a_prop makes the bound NaN: nothing is dropped)
        vw = math.sqrt(d) * (float(np.abs(v).max(initial=0.0)) + half_max)
        redundant = gap > margin * np.maximum(1.0, norm) + _GUARD * (d + 2) * (vw * norm + np.abs(c))
        # rows with a NaN/Inf entry (an infinite or NaN C_jk makes norm so, c_j enters directly)
        nonfinite = ~np.isfinite(norm + c)
    return (mask & ~redundant) | nonfinite


def kept_rows(a_prop, rows: SafetyRows, lo=DEFAULT_LO, hi=DEFAULT_HI, config: QPConfig | None = None) -> np.ndarray:
    """[B, M] bool: the rows ``drop_box_redundant_rows`` keeps (see there): masked-in
    rows that are not box-redundant, plus any row with a NaN/Inf entry."""
    a, C, c, mask, fixed = _arrays(a_prop, rows)
    return _keep(a, C, c, mask, fixed, lo, hi, config)


def drop_box_redundant_rows(a_prop, rows: SafetyRows, lo=DEFAULT_LO, hi=DEFAULT_HI,
                            config: QPConfig | None = None) -> SafetyRows:
    """The rows the QP over ``lo <= a <= hi`` (fixed columns at ``a_prop``) can need.

    a_prop [B, d]; rows C [B, M, d], c [B, M], row_mask [B, M], fixed_mask [B, d] or [d];
    lo/hi scalar, [d] or [B, d] (default: solve_cbf_qp's default box).

    Drops masked-out rows and every box-redundant row (module docstring):
    min over the box of ``C_j a - c_j`` > ``margin * max(1, ||C_j||)`` + a bound on
    the rounding error of that minimum, with ``margin = max(MARGIN_REL,
    10 * max(config.tol, config.active_tol))``. Kept rows are moved to the front
    of each problem in their original order; M' = the largest kept count of the
    batch (at least 1), the rest padded with zero rows, c = 0, row_mask False.
    Returns float64 C [B, M', d], c [B, M'], bool row_mask [B, M'], bool fixed_mask [B, d].

    Exact: ``solve_cbf_qp(a_prop, *pruned)`` gives the same a_exec (to rounding),
    status and slack as on the full rows, feasible or infeasible (slack QP) alike,
    provided the solve uses the same box ``lo``/``hi``. Rows with a NaN/Inf entry are
    always kept, even masked out, so the solver still rejects such a request.
    Raises InvalidQPInput (a ValueError) on disagreeing shapes or a non-finite or
    empty box, which solve_cbf_qp refuses as well.
    """
    a, C, c, mask, fixed = _arrays(a_prop, rows)
    keep = _keep(a, C, c, mask, fixed, lo, hi, config)
    C_out, c_out, row_out = compact_rows_kernel(np.require(C, np.float64, "CA"), np.require(c, np.float64, "CA"),
                                                np.require(mask, np.bool_, "CA"), keep)
    return SafetyRows(C_out, c_out, row_out, np.array(fixed, dtype=bool))
