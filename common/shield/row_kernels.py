"""Compiled loops over a request's safety rows, run by the actor every step:
box-redundant row pruning (common/shield/prune.py) and the check of a shield
answer (common/shield/verify.py). Each is one pass over ``[B, M, d]`` that
the numpy versions spread over a dozen array operations (about 0.1 ms each at
B = 16, a fixed cost a pipelined actor pays twice per step). The numpy
versions are the references these are tested against (tests/test_row_kernels.py):
common/shield/reference.py for the pruning (its keep mask ``prune._keep_fallback`` is
also production's path for a per-column box) and ``verify.verify_answer_fallback``
(production's path for a status array of another type) for the check; the arithmetic
is the same, summed in another order (equal to rounding).
"""
from __future__ import annotations

import math

import numpy as np
from numba import njit


@njit(cache=True, nogil=True)
def keep_rows_kernel(a, C, c, mask, fixed, mid, half, margin, guard):
    """[B, M] bool: rows prune.py keeps over the scalar box ``mid +- half``
    (masked-in and not box-redundant, or with a non-finite entry), computed as
    ``prune._keep``: gap = C v - |C| w - c with v = a_prop on fixed columns and
    ``mid`` elsewhere, w = 0 on fixed columns and ``half`` elsewhere."""
    B, M, d = C.shape
    keep = np.zeros((B, M), dtype=np.bool_)
    sqrt_d = math.sqrt(d)
    vmax = 0.0   # max over the batch of |v|, NaN-propagating as numpy's max
    for b in range(B):
        for k in range(d):
            x = abs(a[b, k]) if fixed[b, k] else abs(mid)
            if vmax == vmax and not (x <= vmax):
                vmax = x
    vw = sqrt_d * (vmax + half)   # the rounding bound's scale (prune._keep_fallback)
    for b in range(B):
        for m in range(M):
            cv = 0.0
            aw = 0.0
            sq = 0.0
            for k in range(d):
                Ck = C[b, m, k]
                if fixed[b, k]:
                    cv += Ck * a[b, k]
                else:
                    cv += Ck * mid
                    aw += abs(Ck) * half
                sq += Ck * Ck
            gap = cv - aw - c[b, m]
            norm = math.sqrt(sq)
            redundant = gap > margin * max(1.0, norm) + guard * (d + 2) * (vw * norm + abs(c[b, m]))
            nonfinite = not math.isfinite(norm + c[b, m])
            keep[b, m] = (mask[b, m] and not redundant) or nonfinite
    return keep


@njit(cache=True, nogil=True)
def compact_rows_kernel(C, c, mask, keep):
    """Kept rows first, in their original order, padded to the largest kept
    count (at least 1) with zero rows, c = 0, row_mask False; a kept row keeps
    its own mask bit (a kept non-finite row stays masked out)."""
    B, M, d = C.shape
    Mp = 1
    for b in range(B):
        n = 0
        for m in range(M):
            if keep[b, m]:
                n += 1
        Mp = max(Mp, n)
    C_out = np.zeros((B, Mp, d))
    c_out = np.zeros((B, Mp))
    row_out = np.zeros((B, Mp), dtype=np.bool_)
    for b in range(B):
        slot = 0
        for m in range(M):
            if keep[b, m]:
                for k in range(d):
                    C_out[b, slot, k] = C[b, m, k]
                c_out[b, slot] = c[b, m]
                row_out[b, slot] = mask[b, m]
                slot += 1
    return C_out, c_out, row_out


# the order verify_answer reports the first failed check in (after "shape")
CHECK_ORDER = ("nonfinite", "box", "fixed_block", "status", "rows")


@njit(cache=True, nogil=True)
def check_answer_kernel(a_prop, a_exec, status, C, c, mask, fixed, tol, optimal, infeasible):
    """verify_answer's checks in one pass: ``failed[i]`` for CHECK_ORDER over
    the whole batch, and each problem's scaled violation
    ``max_masked (c_i - C_i a_exec) / max(1, ||C_i||)`` (-inf without live rows).
    "rows" is checked on problems not claimed infeasible."""
    B, M, d = C.shape
    failed = np.zeros(5, dtype=np.bool_)
    violation = np.full(B, -np.inf)
    for b in range(B):
        for k in range(d):
            x = a_exec[b, k]
            if not math.isfinite(x):
                failed[0] = True
            elif abs(x) > 1.0 + tol:
                failed[1] = True
            if fixed[b, k] and not (x == a_prop[b, k]):
                failed[2] = True
        s = status[b]
        if s != optimal and s != infeasible:
            failed[3] = True
        worst = -np.inf
        for m in range(M):
            if not mask[b, m]:
                continue
            dot = 0.0
            sq = 0.0
            for k in range(d):
                dot += C[b, m, k] * a_exec[b, k]
                sq += C[b, m, k] * C[b, m, k]
            r = (c[b, m] - dot) / max(1.0, math.sqrt(sq))
            if worst == worst and not (r <= worst):   # NaN-propagating, as numpy's max
                worst = r
        violation[b] = worst
        if s != infeasible and worst > tol:
            failed[4] = True
    return failed, violation
