"""Numba kernel of the numpy SAIL solver's damped Newton loop (common/policy/sail.py).

``sail_newton`` is a loop-over-samples version of the Newton loop of
``reference.sail_project`` (and of its line search ``reference.line_search``; common/policy/reference.py); the
caller (``sail.sail_project_np``) validates the inputs, absorbs the fixed (human) columns
and normalizes the rows first, exactly as the reference does. Per sample the kernel
follows the reference step by step: the active rows (positive residual, kept), the
gradient, H = I + kappa C_A^T C_A (SPD, H >= I: solved by Cholesky, d = 9), the
"exact" test (the full step keeps the active set: accept it, this sample is done, for
both dampings), otherwise t from the closed-form exact line search (``damping="exact"``:
the same breakpoints, the same lo / hi / mid / slope rules, t = 1 where the slope is not
positive) or t = 1 (``damping="none"``). Sums use the same products in the same
association (e.g. kappa * sum_j r_j C_j, then subtracted), so results agree with the
reference to rounding; the reference's matrix products go through BLAS, whose summation
order is not reproduced, so agreement is to rounding, not bitwise, and a residual that
is zero to rounding may be classified differently (tests/test_sail_kernel.py).

Masked and zero rows (``keep`` False) are dropped up front: in the reference they are
zero rows with zero right-hand side, never active, and add exact zeros to every sum.
Likewise the gradient and H sum over the active rows only (in row order), and with no
active row the solve is skipped: H = I, and dx = -grad is what the solve gives exactly.
``sail_implicit_step`` gives the learner the constants of its implicit step at a solution
x* (``sail.sail_center_implicit``): H^{-1} over the rows active at x*, from the same
Cholesky factor, and x* - kappa C_J^T r_J. ``sail_newton_implicit``, what the learner
calls, is the loop and those constants in one pass (the last exact step's factor is the one
needed), optionally from a warm start.

``sail_prepare`` is the row preparation both solvers start from (fixed columns absorbed,
rows normalized), one pass instead of numpy's dozen calls.

The kernels loop over the batch inside the compiled function (one core, no threads) and
release the interpreter lock (``nogil``), so they run in an actor or learner thread beside
the others.
"""
from __future__ import annotations

import math

import numpy as np
from numba import njit


@njit(cache=True, inline="always")
def _npmax(u, v):
    """``np.maximum`` of two floats (NaN propagates)."""
    if u != u:
        return u
    if v != v:
        return v
    return u if u >= v else v


@njit(cache=True, inline="always")
def _npmin(u, v):
    """``np.minimum`` of two floats (NaN propagates)."""
    if u != u:
        return u
    if v != v:
        return v
    return u if u <= v else v


@njit(cache=True, inline="always")
def _residuals(Ck, ck, m, x, out):
    """``out[j] = ck[j] - Ck[j] . x`` for the first ``m`` rows."""
    d = x.shape[0]
    for j in range(m):
        acc = 0.0
        for k in range(d):
            acc += Ck[j, k] * x[k]
        out[j] = ck[j] - acc


@njit(cache=True, inline="always")
def _cholesky_factor(H, L):
    """Lower-triangular ``L`` with ``H = L L^T`` for SPD ``H [d,d]`` (reads the lower triangle)."""
    d = H.shape[0]
    for j in range(d):
        acc = H[j, j]
        for k in range(j):
            acc -= L[j, k] * L[j, k]
        ljj = math.sqrt(acc)
        L[j, j] = ljj
        for i in range(j + 1, d):
            acc = H[i, j]
            for k in range(j):
                acc -= L[i, k] * L[j, k]
            L[i, j] = acc / ljj


@njit(cache=True, inline="always")
def _cholesky_solve(H, g, L, z, out):
    """``out = -H^{-1} g`` for SPD ``H [d,d]`` (reads the lower triangle; factor in ``L``, scratch ``z``)."""
    d = g.shape[0]
    _cholesky_factor(H, L)
    for i in range(d):  # L z = g
        acc = g[i]
        for k in range(i):
            acc -= L[i, k] * z[k]
        z[i] = acc / L[i, i]
    for i in range(d - 1, -1, -1):  # L^T w = z, out = -w
        acc = z[i]
        for k in range(i + 1, d):
            acc -= L[k, i] * out[k]
        out[i] = acc / L[i, i]
    for i in range(d):
        out[i] = -out[i]


@njit(cache=True, inline="always")
def _penalty_hessian(Ck, ia, na, kap, H):
    """Lower triangle of H = I + kappa C_A^T C_A over the active rows ``Ck[ia[:na]]``,
    summed in row order."""
    d = H.shape[0]
    for i in range(d):
        for k in range(i + 1):
            H[i, k] = 0.0
    for n in range(na):
        j = ia[n]
        for i in range(d):
            cji = Ck[j, i]
            for k in range(i + 1):
                H[i, k] += cji * Ck[j, k]
    for i in range(d):
        for k in range(i):
            H[i, k] = kap * H[i, k]
        H[i, i] = kap * H[i, i] + 1.0


@njit(cache=True, inline="always")
def _dphi(t, g0, q, kap, r, s, m):
    """phi'(t) = g0 + t q - kappa sum_j [r_j - t s_j]_+ s_j (``reference.line_search``'s ``dphi``)."""
    acc = 0.0
    for j in range(m):
        h = _npmax(r[j] - t * s[j], 0.0)
        acc += h * s[j]
    return g0 + t * q - kap * acc


@njit(cache=True, inline="always")
def _line_search(x, dx, a, Ck, r, m, kap, s, tb, valid):
    """``reference.line_search`` for one sample: argmin_{t >= 0} f(x + t dx) in closed form.

    ``r [m]`` the residuals at x (kept rows); ``s``, ``tb``, ``valid`` scratch [M]."""
    d = x.shape[0]
    for j in range(m):
        acc = 0.0
        for k in range(d):
            acc += Ck[j, k] * dx[k]
        s[j] = acc
    g0 = 0.0
    q = 0.0
    for k in range(d):
        g0 += (x[k] - a[k]) * dx[k]
        q += dx[k] * dx[k]
    lo = 0.0
    hi = np.inf
    for j in range(m):  # breakpoints: rows that switch on/off at a positive step
        valid[j] = False
        tb[j] = 0.0
        if s[j] != 0.0:
            tj = r[j] / s[j]
            if tj > 0.0:
                valid[j] = True
                tb[j] = tj
    for j in range(m):
        if valid[j]:
            if _dphi(tb[j], g0, q, kap, r, s, m) < 0.0:  # still descending there
                lo = _npmax(lo, tb[j])
            else:
                hi = _npmin(hi, tb[j])
    mid = 0.5 * (lo + hi) if np.isfinite(hi) else lo + 1.0
    acc = 0.0
    for j in range(m):  # rows penalized on (lo, hi), where phi' is linear
        if r[j] - mid * s[j] > 0.0:
            acc += s[j] * s[j]
    slope = q + kap * acc
    if not slope > 0.0:
        return 1.0
    t = lo - _dphi(lo, g0, q, kap, r, s, m) / slope
    return _npmin(_npmax(t, lo), hi)


@njit(cache=True, inline="always")
def _kept_rows(Cn_b, cn_b, keep_b, Ck, ck):
    """The kept rows of one sample, in order, into ``Ck``, ``ck``; returns their count."""
    M, d = Cn_b.shape
    m = 0
    for j in range(M):
        if keep_b[j]:
            for k in range(d):
                Ck[m, k] = Cn_b[j, k]
            ck[m] = cn_b[j]
            m += 1
    return m


@njit(cache=True, inline="always")
def _newton_sample(ab, x0, Ck, ck, m, kap, n_newton, exact_damping, x, resid, act, ia, s, tb, valid,
                   g, dx, y, H, L, z, r_y):
    """The damped Newton loop of ``reference.sail_project`` for one sample (kept rows
    ``Ck[:m]``, ``ck[:m]``, target ``ab``), from x = ``x0`` (``x`` holds the iterate). Returns the
    number of active rows ``na`` if the loop ended on an exact step (the full step kept the
    active set, so x is that piece's minimizer), -1 if it ran out of steps. On an exact
    exit the active rows at x are ``ia[:na]`` (in order), ``r_y[:m]`` the residuals there,
    and ``L`` (where na > 0) the Cholesky factor of H = I + kappa C_A^T C_A over them."""
    d = x.shape[0]
    for k in range(d):
        x[k] = x0[k]
    for _ in range(n_newton):
        _residuals(Ck, ck, m, x, resid)
        na = 0
        for j in range(m):
            act[j] = resid[j] > 0.0
            if act[j]:
                ia[na] = j
                na += 1
        for k in range(d):  # grad = (x - a) - kappa C_A^T r_A
            acc = 0.0
            for n in range(na):
                acc += resid[ia[n]] * Ck[ia[n], k]
            g[k] = (x[k] - ab[k]) - kap * acc
        if na == 0:  # H = I: the Cholesky solve gives exactly -grad
            for k in range(d):
                dx[k] = -g[k]
        else:
            _penalty_hessian(Ck, ia, na, kap, H)
            _cholesky_solve(H, g, L, z, dx)
        for k in range(d):
            y[k] = x[k] + dx[k]
        exact = True  # the full step keeps the active set: the minimizer of this piece
        for j in range(m):
            acc = 0.0
            for k in range(d):
                acc += Ck[j, k] * y[k]
            r_y[j] = ck[j] - acc
            if (r_y[j] > 0.0) != act[j]:
                exact = False
                break
        t = 1.0
        if exact_damping and not exact:
            t = _line_search(x, dx, ab, Ck, resid, m, kap, s, tb, valid)
        for k in range(d):
            x[k] = x[k] + t * dx[k]
        if exact:
            return na
    return -1


@njit(cache=True, inline="always")
def _workspace(M, d):
    """Scratch of one sample's solve: (Ck, ck, resid, act, ia, s, tb, valid, g, dx, y, H, L, z, r_y)."""
    return (np.empty((M, d)), np.empty(M), np.empty(M), np.empty(M, dtype=np.bool_), np.empty(M, dtype=np.int64),
            np.empty(M), np.empty(M), np.empty(M, dtype=np.bool_), np.empty(d), np.empty(d), np.empty(d),
            np.empty((d, d)), np.zeros((d, d)), np.empty(d), np.empty(M))


@njit(cache=True, nogil=True)
def sail_newton(a, Cn, cn, keep, kappa, n_newton, exact_damping):
    """The damped Newton loop of ``reference.sail_project`` over the batch.

    a [B,d], Cn [B,M,d], cn [B,M] (fixed columns absorbed, rows normalized), keep [B,M]
    bool, kappa [B] (>= 0), n_newton >= 0, exact_damping (``damping == "exact"``).
    Returns x [B,d] (float64)."""
    B, M, d = Cn.shape
    out = np.empty((B, d))
    Ck, ck, resid, act, ia, s, tb, valid, g, dx, y, H, L, z, r_y = _workspace(M, d)
    for b in range(B):
        m = _kept_rows(Cn[b], cn[b], keep[b], Ck, ck)
        _newton_sample(a[b], a[b], Ck, ck, m, kappa[b], n_newton, exact_damping, out[b], resid, act, ia, s, tb,
                       valid, g, dx, y, H, L, z, r_y)
    return out


@njit(cache=True, inline="always")
def _inverse_from_factor(L, Li, H_inv):
    """H^{-1} = L^{-T} L^{-1} (symmetric, both triangles) from the Cholesky factor ``L``; ``Li`` scratch."""
    d = L.shape[0]
    for k in range(d):                          # Li = L^{-1} (lower triangular)
        for i in range(d):
            Li[i, k] = 0.0
        Li[k, k] = 1.0 / L[k, k]
        for i in range(k + 1, d):
            acc = 0.0
            for m in range(k, i):
                acc += L[i, m] * Li[m, k]
            Li[i, k] = -acc / L[i, i]
    for i in range(d):                          # H^{-1} = Li^T Li (symmetric)
        for k in range(i + 1):
            acc = 0.0
            for m in range(i, d):
                acc += Li[m, i] * Li[m, k]
            H_inv[i, k] = acc
            H_inv[k, i] = acc


@njit(cache=True, inline="always")
def _step_constants(x, Cr, r, ia, na, kap, H, L, Li, factored, H_inv, offset):
    """The implicit step's constants at a solution x over its active rows ``Cr[ia[:na]]``
    (residuals ``r`` indexed the same way): offset = x - kappa C_J^T r_J and H^{-1}, from the
    Cholesky factor already in ``L`` where ``factored``."""
    d = x.shape[0]
    for i in range(d):
        acc = 0.0
        for n in range(na):
            acc += r[ia[n]] * Cr[ia[n], i]
        offset[i] = x[i] - kap * acc
    if na == 0:   # H = I
        for i in range(d):
            for k in range(d):
                H_inv[i, k] = 1.0 if i == k else 0.0
        return
    if not factored:
        _penalty_hessian(Cr, ia, na, kap, H)
        _cholesky_factor(H, L)                  # H = L L^T
    _inverse_from_factor(L, Li, H_inv)


@njit(cache=True, inline="always")
def _implicit_sample(x, Cb, cb, keep_b, kap, r, ia, H, L, Li, H_inv, offset):
    """``sail_implicit_step`` for one sample: the rows active at x (kept, positive residual)."""
    M = Cb.shape[0]
    _residuals(Cb, cb, M, x, r)
    na = 0
    for j in range(M):   # the active rows, in order (as sail_newton sums them)
        if keep_b[j] and r[j] > 0.0:
            ia[na] = j
            na += 1
    _step_constants(x, Cb, r, ia, na, kap, H, L, Li, False, H_inv, offset)


@njit(cache=True, nogil=True)
def sail_implicit_step(x_star, Cn, cn, keep, kappa):
    """The constants of the learner's implicit SAIL step at a solution ``x_star [B,d]``
    (same prepared rows as ``sail_newton``): ``H^{-1}`` with H = I + kappa C_J^T C_J over
    the rows active at x* (kept, positive residual), and ``offset = x* - kappa C_J^T r_J``,
    so that the step x* - H^{-1} [(x* - a) - kappa C_J^T r_J] is x* - H^{-1} (offset - a).
    Returns (H_inv [B,d,d], offset [B,d]); H^{-1} = L^{-T} L^{-1} from the Cholesky factor."""
    B, M, d = Cn.shape
    H_inv = np.empty((B, d, d))
    offset = np.empty((B, d))
    H = np.empty((d, d))
    L = np.zeros((d, d))
    Li = np.empty((d, d))
    r = np.empty(M)
    ia = np.empty(M, dtype=np.int64)
    for b in range(B):
        _implicit_sample(x_star[b], Cn[b], cn[b], keep[b], kappa[b], r, ia, H, L, Li, H_inv[b], offset[b])
    return H_inv, offset


@njit(cache=True, nogil=True)
def sail_newton_implicit(a, Cn, cn, keep, kappa, n_newton, exact_damping, x0):
    """``sail_newton`` and ``sail_implicit_step`` at its answer in one pass, the same bits:
    where the loop ends on an exact step the rows active at x* are the last step's (that is
    what exact means), so H, its Cholesky factor and the residuals there are the ones the
    loop just computed, in the same order; otherwise (out of steps) they are computed
    afresh at x* as ``sail_implicit_step`` does. Returns (x [B,d], H_inv [B,d,d], offset [B,d]).

    ``x0`` [B,d]: where each sample's loop starts (a warm start, e.g. the solution at nearby
    a); empty [0,d]: at ``a``, as ``sail_newton``. A warm start is kept only where its loop
    ends on an exact step (then x* is the minimizer, the same as from ``a`` to rounding, in
    fewer steps); elsewhere the sample is solved again from ``a``, so that a budget that
    runs out leaves ``sail_newton``'s own iterate."""
    B, M, d = Cn.shape
    out = np.empty((B, d))
    H_inv = np.empty((B, d, d))
    offset = np.empty((B, d))
    Li = np.empty((d, d))
    Ck, ck, resid, act, ia, s, tb, valid, g, dx, y, H, L, z, r_y = _workspace(M, d)
    warm = x0.shape[0] == B and B > 0
    for b in range(B):
        kap = kappa[b]
        m = _kept_rows(Cn[b], cn[b], keep[b], Ck, ck)
        na = -1
        if warm:
            na = _newton_sample(a[b], x0[b], Ck, ck, m, kap, n_newton, exact_damping, out[b], resid, act, ia, s, tb,
                                valid, g, dx, y, H, L, z, r_y)
        if na < 0:
            na = _newton_sample(a[b], a[b], Ck, ck, m, kap, n_newton, exact_damping, out[b], resid, act, ia, s, tb,
                                valid, g, dx, y, H, L, z, r_y)
        if na >= 0:
            _step_constants(out[b], Ck, r_y, ia, na, kap, H, L, Li, True, H_inv[b], offset[b])
        else:
            _implicit_sample(out[b], Cn[b], cn[b], keep[b], kap, resid, ia, H, L, Li, H_inv[b], offset[b])
    return out, H_inv, offset


@njit(cache=True, nogil=True)
def sail_prepare(a, C, c, mask, fixed, human, row_tol):
    """``sail._prepare_np``'s row preparation in one pass (its numpy twin: ``absorb_fixed`` then
    ``normalize_rows``): the fixed (human) columns of each row moved to the right-hand side,
    c_j - sum_{k fixed} C_jk h_k, and zeroed; each row with ||C_j|| > row_tol and unmasked
    scaled to unit norm (with its right-hand side), the others zeroed and not kept; the fixed
    entries of a replaced by the human's. a, fixed, human [B,d], C [B,M,d], c, mask [B,M].
    Returns (a, Cn, cn, keep)."""
    B, M, d = C.shape
    a_out = np.empty((B, d))
    Cn = np.empty((B, M, d))
    cn = np.empty((B, M))
    keep = np.empty((B, M), dtype=np.bool_)
    for b in range(B):
        for k in range(d):
            a_out[b, k] = human[b, k] if fixed[b, k] else a[b, k]
        for j in range(M):
            shift = 0.0
            sq = 0.0
            for k in range(d):
                v = C[b, j, k]
                if fixed[b, k]:
                    shift += v * human[b, k]
                else:
                    sq += v * v
            norm = math.sqrt(sq)
            kept = mask[b, j] and norm > row_tol
            keep[b, j] = kept
            inv = 1.0 / norm if kept else 0.0
            for k in range(d):
                Cn[b, j, k] = 0.0 if fixed[b, k] else C[b, j, k] * inv
            cn[b, j] = (c[b, j] - shift) * inv
    return a_out, Cn, cn, keep
