"""The QP solver of the exact joint CBF-QP shield (Eq. qpshield): numba kernels.

Two independent pieces live here:

* ``solve_batch_active_set``: a Goldfarb–Idnani dual active-set solver for
  ``min ½‖y − y0‖²  s.t.  N y ≥ b`` (Hessian = I, so the factor ``J`` starts as
  the identity). The action box enters as ordinary rows ``±e_k``. Infeasible
  row sets fall back to the slack QP documented in ``common/shield/qp.py``.
* ``diagnostics_batch``: KKT residuals computed from the returned primal only,
  with multipliers re-derived by a separate Lawson–Hanson NNLS, so a bug in the
  solver cannot hide itself in its own certificate.

Both loop over the batch inside the compiled function (one core, no threads) and
release the interpreter lock (``nogil``), so an in-process shield thread solves
while the actor and learner threads run.
"""
from __future__ import annotations

import math

import numpy as np
from numba import njit

STATUS_OPTIMAL = 0
STATUS_INFEASIBLE = 1
STATUS_MAX_ITER = 2

# Internal return codes of the Goldfarb–Idnani core.
_GI_OK = 0
_GI_INFEASIBLE = 1
_GI_MAX_ITER = 2


@njit(cache=True, nogil=True)
def _gi_drop(l, q, n, R, JT, u, act, in_act):
    """Remove active constraint number ``l`` and restore R to triangular form.

    Invariant kept: row i = act[j] satisfies Jᵀ N_i = [R[:q, j]; 0] with J
    orthogonal (stored transposed, JT = Jᵀ, for contiguous access). Deleting
    column l leaves R upper Hessenberg; Givens rotations on rows (j, j+1) of R
    and of JT restore it.
    """
    in_act[act[l]] = False
    for j in range(l, q - 1):
        act[j] = act[j + 1]
        u[j] = u[j + 1]
        for k in range(j + 2):
            R[k, j] = R[k, j + 1]
    for j in range(l, q - 1):
        a = R[j, j]
        bb = R[j + 1, j]
        if bb != 0.0:
            h = math.hypot(a, bb)
            cs = a / h
            sn = bb / h
            for col in range(j, q - 1):
                r1 = R[j, col]
                r2 = R[j + 1, col]
                R[j, col] = cs * r1 + sn * r2
                R[j + 1, col] = -sn * r1 + cs * r2
            for k in range(n):
                j1 = JT[j, k]
                j2 = JT[j + 1, k]
                JT[j, k] = cs * j1 + sn * j2
                JT[j + 1, k] = -sn * j1 + cs * j2
        R[j + 1, j] = 0.0
    return q - 1


@njit(cache=True, nogil=True)
def _gi_solve(y0, NT, b, norms, mg, bvar, bsign, m, n, tol, dep_tol, max_iter,
              y, JT, R, u, act, in_act, dvec, z, r, sres):
    """Goldfarb–Idnani dual active set for min ½‖y − y0‖² s.t. rows(y) ≥ b[:m].

    Rows 0..mg−1 are dense (NT[:n, i], stored transposed); rows mg..m−1 are bounds bsign[i]·y[bvar[i]]
    (the action box and slack signs), which cost O(1) to evaluate.
    Starts at the unconstrained minimizer y0 (dual feasible) and repeatedly
    adds the most violated row (normalized by its norm); a row that no primal
    step can reach while no active multiplier can shrink proves the row set
    infeasible. Returns (code, iterations, q): active set act[:q], multipliers u[:q].
    """
    for i in range(n):
        y[i] = y0[i]
        for j in range(n):
            JT[i, j] = 1.0 if i == j else 0.0
    for i in range(m):
        in_act[i] = False
    q = 0
    it = 0
    while True:
        # Step 1: most violated row (violation measured in row-normalized units).
        p = -1
        worst = 0.0
        # Residuals of all dense rows at once: NT is stored column-major (NT[k, i]) so
        # the inner loop runs over independent rows and vectorizes.
        for i in range(mg):
            sres[i] = -b[i]
        for k in range(n):
            yk = y[k]
            for i in range(mg):
                sres[i] += NT[k, i] * yk
        for i in range(m):
            if in_act[i]:
                continue
            if i < mg:
                si = sres[i]
            else:
                si = bsign[i] * y[bvar[i]] - b[i]
            if si < -tol * max(norms[i], 1.0):
                v = si / norms[i]
                if v < worst:
                    worst = v
                    p = i
        if p < 0:
            return _GI_OK, it, q
        up = 0.0
        # Step 2: move toward row p, dropping rows whose multiplier hits zero.
        while True:
            it += 1
            if it > max_iter:
                return _GI_MAX_ITER, it, q
            if p >= mg:  # d = Jᵀ n_p
                for j in range(n):
                    dvec[j] = bsign[p] * JT[j, bvar[p]]
            else:
                for j in range(n):
                    acc = 0.0
                    for k in range(n):
                        acc += JT[j, k] * NT[k, p]
                    dvec[j] = acc
            zn2 = 0.0
            for k in range(n):
                z[k] = 0.0
            for j in range(q, n):  # z = J₂ d₂: primal direction in the null space of the active rows
                dj = dvec[j]
                zn2 += dj * dj
                for k in range(n):
                    z[k] += JT[j, k] * dj
            for j in range(q - 1, -1, -1):  # r = R⁻¹ d₁: dual direction
                acc = dvec[j]
                for l2 in range(j + 1, q):
                    acc -= R[j, l2] * r[l2]
                r[j] = acc / R[j, j]
            # Partial (dual) step length: first active multiplier to reach zero.
            t1 = np.inf
            l = -1
            for j in range(q):
                if r[j] > 0.0:
                    ratio = u[j] / r[j]
                    if ratio < t1:
                        t1 = ratio
                        l = j
            # Full (primal) step length: reach row p along z.
            t2 = np.inf
            if zn2 > (dep_tol * norms[p]) ** 2:
                if p < mg:
                    sp = -b[p]
                    zn = 0.0
                    for k in range(n):
                        sp += NT[k, p] * y[k]
                        zn += NT[k, p] * z[k]
                else:
                    sp = bsign[p] * y[bvar[p]] - b[p]
                    zn = bsign[p] * z[bvar[p]]
                t2 = max(-sp / zn, 0.0)
            if t1 == np.inf and t2 == np.inf:
                return _GI_INFEASIBLE, it, q
            if t2 == np.inf:
                # Row p is dependent on the active rows: shift weight to it, drop row l.
                for j in range(q):
                    u[j] -= t1 * r[j]
                up += t1
                q = _gi_drop(l, q, n, R, JT, u, act, in_act)
                continue
            t = min(t1, t2)
            for k in range(n):
                y[k] += t * z[k]
            for j in range(q):
                u[j] -= t * r[j]
            up += t
            if t2 <= t1:
                # Full step: add p. Rotate d = Jᵀ n_p so that d[q+1:] = 0.
                for j in range(n - 1, q, -1):
                    if dvec[j] != 0.0:
                        h = math.hypot(dvec[j - 1], dvec[j])
                        cs = dvec[j - 1] / h
                        sn = dvec[j] / h
                        dvec[j - 1] = h
                        dvec[j] = 0.0
                        for k in range(n):
                            j1 = JT[j - 1, k]
                            j2 = JT[j, k]
                            JT[j - 1, k] = cs * j1 + sn * j2
                            JT[j, k] = -sn * j1 + cs * j2
                for k in range(q + 1):
                    R[k, q] = dvec[k]
                act[q] = p
                u[q] = up
                in_act[p] = True
                q += 1
                break
            q = _gi_drop(l, q, n, R, JT, u, act, in_act)


@njit(cache=True, nogil=True)
def _append_box_rows(m, nf, free, lo, hi, bvar, bsign, bvec, norms):
    """The box as ordinary bound rows from slot ``m`` on: x_k ≥ lo_k and −x_k ≥ −hi_k
    for every free variable k. Returns the next free slot."""
    for kk in range(nf):
        bvar[m] = kk
        bsign[m] = 1.0
        bvec[m] = lo[free[kk]]
        norms[m] = 1.0
        bvar[m + 1] = kk
        bsign[m + 1] = -1.0
        bvec[m + 1] = -hi[free[kk]]
        norms[m + 1] = 1.0
        m += 2
    return m


@njit(cache=True, nogil=True)
def solve_batch_active_set(a, C, c, row_mask, fixed, lo, hi, tol, dep_tol, zero_tol,
                           max_iter, rho, x_out, status, iters):
    """Solve B projections Eq. (qpshield) with the box and fixed variables.

    Fixed variables are substituted (c ← c − C_F a_F) and only the free ones are
    optimized. Infeasible row sets are re-solved as the lifted slack QP
        min ½‖x − a‖² + ½‖σ‖²  s.t.  C_i x + σ_i/√ρ ≥ c_i,  σ ≥ 0,  lo ≤ x ≤ hi,
    i.e. slack s = σ/√ρ with penalty ρ/2‖s‖², which is again an identity-Hessian
    QP and always feasible, so the same core solves it.
    """
    B, M, d = C.shape
    nl = d + M
    ml = 2 * M + 2 * d
    NT = np.zeros((nl, M))  # dense rows, transposed
    sres = np.zeros(M)
    bvec = np.zeros(ml)
    norms = np.ones(ml)
    bvar = np.zeros(ml, dtype=np.int64)
    bsign = np.zeros(ml)
    y0 = np.zeros(nl)
    y = np.zeros(nl)
    JT = np.zeros((nl, nl))
    R = np.zeros((nl, nl))
    u = np.zeros(nl)
    act = np.zeros(nl, dtype=np.int64)
    in_act = np.zeros(ml, dtype=np.bool_)
    dvec = np.zeros(nl)
    z = np.zeros(nl)
    r = np.zeros(nl)
    free = np.zeros(d, dtype=np.int64)
    cp = np.zeros(M)
    inv_sqrt_rho = 1.0 / math.sqrt(rho)
    for bi in range(B):
        for k in range(d):
            x_out[bi, k] = a[bi, k]
        nf = 0
        for k in range(d):
            if not fixed[bi, k]:
                free[nf] = k
                nf += 1
        # Substitute the fixed block into the rows; sort out rows with no free part.
        mr = 0
        zero_violated = False
        for i in range(M):
            if not row_mask[bi, i]:
                continue
            ci = c[bi, i]
            for k in range(d):
                if fixed[bi, k]:
                    ci -= C[bi, i, k] * a[bi, k]
            nrm2 = 0.0
            for kk in range(nf):
                v = C[bi, i, free[kk]]
                NT[kk, mr] = v
                nrm2 += v * v
            nrm = math.sqrt(nrm2)
            if nrm <= zero_tol:
                if ci > tol:
                    zero_violated = True  # a constant row that no free action can fix
                continue
            cp[mr] = ci
            bvec[mr] = ci
            norms[mr] = nrm
            mr += 1
        if nf == 0:
            status[bi] = STATUS_INFEASIBLE if zero_violated else STATUS_OPTIMAL
            iters[bi] = 0
            continue
        for kk in range(nf):
            y0[kk] = a[bi, free[kk]]
        code = _GI_INFEASIBLE
        it = 0
        if not zero_violated:
            m = _append_box_rows(mr, nf, free, lo[bi], hi[bi], bvar, bsign, bvec, norms)
            code, it, q = _gi_solve(y0, NT, bvec, norms, mr, bvar, bsign, m, nf, tol, dep_tol,
                                    max_iter, y, JT, R, u, act, in_act, dvec, z, r, sres)
        if code == _GI_INFEASIBLE:
            # Lifted slack QP over y = (x_free, σ): rows [C_i, e_i/√ρ] y ≥ c_i, σ ≥ 0, box.
            n2 = nf + mr
            for ii in range(mr):
                nrm2 = 0.0
                for kk in range(nf):
                    nrm2 += NT[kk, ii] * NT[kk, ii]
                for j in range(nf, n2):
                    NT[j, ii] = 0.0
                NT[nf + ii, ii] = inv_sqrt_rho
                bvec[ii] = cp[ii]
                norms[ii] = math.sqrt(nrm2 + inv_sqrt_rho * inv_sqrt_rho)
                y0[nf + ii] = 0.0
            m = mr
            for ii in range(mr):  # σ_i ≥ 0
                bvar[m] = nf + ii
                bsign[m] = 1.0
                bvec[m] = 0.0
                norms[m] = 1.0
                m += 1
            m = _append_box_rows(m, nf, free, lo[bi], hi[bi], bvar, bsign, bvec, norms)
            code2, it2, q = _gi_solve(y0, NT, bvec, norms, mr, bvar, bsign, m, n2, tol, dep_tol,
                                      max_iter, y, JT, R, u, act, in_act, dvec, z, r, sres)
            it += it2
            status[bi] = STATUS_INFEASIBLE if code2 == _GI_OK else STATUS_MAX_ITER
        elif code == _GI_OK:
            status[bi] = STATUS_OPTIMAL
        else:
            status[bi] = STATUS_MAX_ITER
        iters[bi] = it
        for kk in range(nf):
            k = free[kk]
            # The box is always respected: clip the last ulp-level excursions.
            x_out[bi, k] = min(max(y[kk], lo[bi, k]), hi[bi, k])


@njit(cache=True, nogil=True)
def _ls_householder(A, idx, p, n, g, W, rhs, zout):
    """Least squares min ‖Σ_j z_j A[idx[j]] − g‖ by Householder QR (p ≤ n columns).

    Returns the smallest |diagonal| of the triangular factor (0 when rank deficient).
    """
    for j in range(p):
        for i in range(n):
            W[i, j] = A[idx[j], i]
    for i in range(n):
        rhs[i] = g[i]
    for j in range(p):
        nx = 0.0
        for i in range(j, n):
            nx += W[i, j] * W[i, j]
        nx = math.sqrt(nx)
        if nx == 0.0:
            continue
        alpha = -nx if W[j, j] >= 0.0 else nx
        v0 = W[j, j] - alpha
        vn2 = v0 * v0
        for i in range(j + 1, n):
            vn2 += W[i, j] * W[i, j]
        if vn2 > 0.0:
            # Apply H = I − 2 v vᵀ / vᵀv (v = [v0, W[j+1:, j]]) to the trailing columns and rhs.
            for col in range(j + 1, p):
                s = v0 * W[j, col]
                for i in range(j + 1, n):
                    s += W[i, j] * W[i, col]
                f = 2.0 * s / vn2
                W[j, col] -= f * v0
                for i in range(j + 1, n):
                    W[i, col] -= f * W[i, j]
            s = v0 * rhs[j]
            for i in range(j + 1, n):
                s += W[i, j] * rhs[i]
            f = 2.0 * s / vn2
            rhs[j] -= f * v0
            for i in range(j + 1, n):
                rhs[i] -= f * W[i, j]
        W[j, j] = alpha
    dmin = np.inf
    for j in range(p - 1, -1, -1):
        acc = rhs[j]
        for l in range(j + 1, p):
            acc -= W[j, l] * zout[l]
        zout[j] = acc / W[j, j] if abs(W[j, j]) > 1e-300 else 0.0
        dmin = min(dmin, abs(W[j, j]))
    return dmin


@njit(cache=True, nogil=True)
def nnls(A, k, n, g, lam, inP, idx, W, rhs, zls, resid):
    """Lawson–Hanson NNLS: min ‖Aᵀλ − g‖ over λ ≥ 0, generators are rows A[:k, :n].

    Returns the residual ∞-norm. Used only to certify KKT (independent of the
    active-set solver's own multipliers).
    """
    for j in range(k):
        lam[j] = 0.0
        inP[j] = False
    gn = 0.0
    for i in range(n):
        resid[i] = g[i]
        gn += g[i] * g[i]
    wtol = 1e-14 * (1.0 + math.sqrt(gn))
    # Fast path: if the plain least-squares weights on all generators are
    # well-determined and positive, they are the NNLS solution.
    if 0 < k <= n:
        for j in range(k):
            idx[j] = j
        dmin = _ls_householder(A, idx, k, n, g, W, rhs, zls)
        ok = dmin > 1e-6
        for j in range(k):
            ok = ok and zls[j] > 0.0
        if ok:
            rmax = 0.0
            for i in range(n):
                acc = g[i]
                for j in range(k):
                    lam[j] = zls[j]
                    acc -= zls[j] * A[j, i]
                rmax = max(rmax, abs(acc))
            return rmax
    p = 0
    for _outer in range(3 * k + 5):
        best = -1
        wbest = 0.0
        for j in range(k):
            if inP[j]:
                continue
            w = 0.0
            an = 0.0
            for i in range(n):
                w += A[j, i] * resid[i]
                an += A[j, i] * A[j, i]
            if w > wtol * max(1.0, math.sqrt(an)) and w > wbest:
                wbest = w
                best = j
        if best < 0 or p >= n:
            break
        inP[best] = True
        idx[p] = best
        p += 1
        for _inner in range(3 * k + 5):
            _ls_householder(A, idx, p, n, g, W, rhs, zls)
            alpha = np.inf
            for jj in range(p):
                if zls[jj] <= 0.0:
                    j = idx[jj]
                    den = lam[j] - zls[jj]
                    ratio = lam[j] / den if den > 0.0 else 0.0
                    if ratio < alpha:
                        alpha = ratio
            if alpha == np.inf:
                for jj in range(p):
                    lam[idx[jj]] = zls[jj]
                break
            for jj in range(p):
                j = idx[jj]
                lam[j] += alpha * (zls[jj] - lam[j])
            # Drop generators whose weight reached zero (keeps the passive set independent).
            newp = 0
            for jj in range(p):
                j = idx[jj]
                if lam[j] <= 1e-15 * (1.0 + abs(zls[jj])):
                    lam[j] = 0.0
                    inP[j] = False
                else:
                    idx[newp] = j
                    newp += 1
            p = newp
            if p == 0:
                break
        for i in range(n):
            acc = g[i]
            for j in range(k):
                acc -= lam[j] * A[j, i]
            resid[i] = acc
        if not inP[best]:
            break  # the newly added generator could not enter: stop (rounding stall)
    rmax = 0.0
    for i in range(n):
        rmax = max(rmax, abs(resid[i]))
    return rmax


@njit(cache=True, nogil=True)
def diagnostics_batch(a, x, C, c, row_mask, fixed, lo, hi, status, rho, act_tol,
                      active, corr, kkt, slack):
    """Per-problem diagnostics from the primal x alone (backend independent).

    KKT residual = max(stationarity, primal infeasibility, dual infeasibility,
    complementarity), with multipliers re-derived by NNLS on the near-active
    rows (|C_i x − c_i| ≤ act_tol·max(1, ‖C_i‖)) and box faces. For
    STATUS_INFEASIBLE the certificate is that of the slack QP: the row
    multipliers are ρ·s_i with s_i = [c_i − C_i x]_+, and only box faces remain
    as inequality multipliers. Dual infeasibility is zero by construction of NNLS.
    """
    B, M, d = C.shape
    mt = M + 2 * d
    A = np.zeros((mt, d))
    sl = np.zeros(mt)
    g = np.zeros(d)
    lam = np.zeros(mt)
    inP = np.zeros(mt, dtype=np.bool_)
    idx = np.zeros(mt, dtype=np.int64)
    W = np.zeros((d, mt))
    rhs = np.zeros(d)
    zls = np.zeros(mt)
    resid = np.zeros(d)
    free = np.zeros(d, dtype=np.int64)
    for bi in range(B):
        nf = 0
        cn = 0.0
        for k in range(d):
            dk = x[bi, k] - a[bi, k]
            cn += dk * dk
            if not fixed[bi, k]:
                free[nf] = k
                nf += 1
        corr[bi] = math.sqrt(cn)
        infeasible = status[bi] == STATUS_INFEASIBLE
        for kk in range(nf):
            g[kk] = x[bi, free[kk]] - a[bi, free[kk]]
        k = 0
        primal = 0.0
        maxviol = 0.0
        for i in range(M):
            active[bi, i] = False
            if not row_mask[bi, i]:
                continue
            si = -c[bi, i]
            nrm2 = 0.0
            for j in range(d):
                si += C[bi, i, j] * x[bi, j]
            for kk in range(nf):
                nrm2 += C[bi, i, free[kk]] ** 2
            viol = max(-si, 0.0)
            maxviol = max(maxviol, viol)
            active[bi, i] = si <= act_tol * max(1.0, math.sqrt(nrm2))
            if infeasible:
                # Slack QP stationarity: x − a − ρ Σ s_i C_i ∈ box normal cone.
                for kk in range(nf):
                    g[kk] -= rho * viol * C[bi, i, free[kk]]
            else:
                primal = max(primal, viol)
                if abs(si) <= act_tol * max(1.0, math.sqrt(nrm2)) and nrm2 > 0.0:
                    for kk in range(nf):
                        A[k, kk] = C[bi, i, free[kk]]
                    sl[k] = si
                    k += 1
        for kk in range(nf):
            j = free[kk]
            lo_gap = x[bi, j] - lo[bi, j]
            hi_gap = hi[bi, j] - x[bi, j]
            primal = max(primal, -lo_gap, -hi_gap)
            for sgn, gap in ((1.0, lo_gap), (-1.0, hi_gap)):
                if abs(gap) <= act_tol:
                    for jj in range(nf):
                        A[k, jj] = 0.0
                    A[k, kk] = sgn
                    sl[k] = gap
                    k += 1
        stat = 0.0
        comp = 0.0
        if nf > 0:
            stat = nnls(A, k, nf, g, lam, inP, idx, W, rhs, zls, resid)
            for j in range(k):
                comp = max(comp, lam[j] * abs(sl[j]))
        kkt[bi] = max(stat, primal, comp)
        slack[bi] = maxviol if infeasible else 0.0
