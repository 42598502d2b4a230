"""Numba kernels of the environment's step (the hot path of ``BatchEnv.step``).

Each kernel is a loop-over-envs version of a numpy reference in common/env/reference.py
(test oracles, not production code): ``reference.signed_distance`` / ``nearest`` /
``ray_distance`` (``WallSet``), ``route_project`` (``Route.project``), ``tracker_targets``,
``grasp_strain``, ``physics_reset`` (``TransportPhysics``), ``snapshot`` / ``observe``
(``observations``), ``step_outcome`` (``task``), ``build_rows`` / ``spec_barrier_min``
(``safety``) and ``start_clearance``, ``place_episodes``, ``add_noise``, ``accumulate``
(``BatchEnv``); tests/test_env_fast.py and tests/test_env_kernels.py check them against
those references. The arithmetic follows
the references operation by operation (same products, same summation order, same
tie-breaking: the first minimum wins, sorts are stable) so results agree to rounding
(numpy's and libm's sin/cos/atan2 may differ in the last bit) and discrete choices
(nearest wall, kept rows) agree exactly. Where a kernel skips walls that cannot change
its result (a signed distance is 1-Lipschitz, so walls far from a body's origin are far
from all its points), the skip is exact. The per-step kernels take the envs to process
as an index array ``envs`` and write those rows of full-size [K, ...] outputs.
The kernels called from Python are ``nogil``: in the in-process placement the actor's
env step then runs beside the learner's and the shield's threads instead of holding
the interpreter lock.
"""
from __future__ import annotations

import math

import numpy as np
from numba import njit

_EPS = 1e-12


# ----------------------------------------------------------------------------- point–box queries
# Walls come as a table ``tab [6,W]``: rows centre x, centre y, half-size x, half-size y, cos and
# sin of the yaw (``geometry.WallSet.table``), so that loops over the walls have unit stride and
# the compiler vectorizes them.

@njit(cache=True, inline="always")
def _box_local(px, py, tab, w):
    """``R(yaw)^T (p - centre)`` of a point in wall ``w``'s frame."""
    dx = px - tab[0, w]
    dy = py - tab[1, w]
    return tab[4, w] * dx + tab[5, w] * dy, -tab[5, w] * dx + tab[4, w] * dy


@njit(cache=True, inline="always")
def _box_sd(lx, ly, hx, hy):
    """Signed distance of a local point to the box ``[-hx, hx] x [-hy, hy]``."""
    qx = abs(lx) - hx
    qy = abs(ly) - hy
    ox = max(qx, 0.0)
    oy = max(qy, 0.0)
    return math.sqrt(ox * ox + oy * oy) + min(max(qx, qy), 0.0)


@njit(cache=True, inline="always")
def _wall_sd(px, py, tab, nw, out):
    """Signed distance of a point to the first ``nw`` walls into ``out[:nw]``."""
    for w in range(nw):
        lx, ly = _box_local(px, py, tab, w)
        out[w] = _box_sd(lx, ly, tab[2, w], tab[3, w])


@njit(cache=True, inline="always")
def _reach(pts_local):
    """Largest distance of body points ``[P,2]`` from their frame's origin, plus a rounding margin."""
    r = 0.0
    for p in range(pts_local.shape[0]):
        r = max(r, math.sqrt(pts_local[p, 0] * pts_local[p, 0] + pts_local[p, 1] * pts_local[p, 1]))
    return r + 1e-9


@njit(cache=True, inline="always")
def _select_walls(sd, limit, tab, out, idx):
    """Copy to ``out [6,W]`` (in order; their indices to ``idx [W]``) the walls whose distance
    ``sd [W]`` from a point is at most ``limit``, and return their number. A signed distance is
    1-Lipschitz, so a wall farther than ``d + r`` from a point is farther than ``d`` from every
    point within ``r`` of it."""
    n = 0
    for w in range(tab.shape[1]):
        if sd[w] <= limit:
            for r in range(6):
                out[r, n] = tab[r, w]
            idx[n] = w
            n += 1
    return n


@njit(cache=True, nogil=True)
def signed_distances(pts, tab, out):
    """``WallSet.signed_distance`` for points ``[N,2]`` into ``out [N,W]``."""
    for p in range(pts.shape[0]):
        _wall_sd(pts[p, 0], pts[p, 1], tab, tab.shape[1], out[p])


@njit(cache=True, inline="always")
def _nearest_wall(px, py, tab, nw, buf):
    """``(distance, vx, vy)``: signed distance of a point to its nearest wall box among the first
    ``nw`` (the first minimum, like argmin) and the vector to that box's closest point; ``buf [W]``
    is scratch."""
    _wall_sd(px, py, tab, nw, buf)
    bw = 0
    for w in range(1, nw):
        if buf[w] < buf[bw]:
            bw = w
    lx, ly = _box_local(px, py, tab, bw)
    bdx = min(max(lx, -tab[2, bw]), tab[2, bw]) - lx
    bdy = min(max(ly, -tab[3, bw]), tab[3, bw]) - ly
    c, s = tab[4, bw], tab[5, bw]
    return buf[bw], c * bdx - s * bdy, s * bdx + c * bdy


@njit(cache=True, nogil=True)
def nearest_walls(pts, tab, dist, vec):
    """``WallSet.nearest`` for points ``[N,2]``: fills ``dist [N]`` and ``vec [N,2]``."""
    buf = np.empty(tab.shape[1])
    for p in range(pts.shape[0]):
        dist[p], vec[p, 0], vec[p, 1] = _nearest_wall(pts[p, 0], pts[p, 1], tab, tab.shape[1], buf)


@njit(cache=True, inline="always")
def _ray_distance(ox, oy, ux, uy, tab, nw, max_dist):
    """Distance along the unit ray ``(ox, oy) + t (ux, uy)`` to the first of the first ``nw`` wall
    boxes (slab test), capped at ``max_dist``."""
    best = np.inf
    for w in range(nw):
        lx, ly = _box_local(ox, oy, tab, w)
        c, s = tab[4, w], tab[5, w]
        dx = c * ux + s * uy
        dy = -s * ux + c * uy
        ix = 1.0 / (1e-12 if abs(dx) < 1e-12 else dx)
        iy = 1.0 / (1e-12 if abs(dy) < 1e-12 else dy)
        hx, hy = tab[2, w], tab[3, w]
        t1x = (-hx - lx) * ix
        t2x = (hx - lx) * ix
        t1y = (-hy - ly) * iy
        t2y = (hy - ly) * iy
        tmin = max(min(t1x, t2x), min(t1y, t2y))
        tmax = min(max(t1x, t2x), max(t1y, t2y))
        t0 = max(tmin, 0.0)
        best = min(best, t0 if tmax >= t0 else max_dist)
    return min(best, max_dist)


@njit(cache=True, nogil=True)
def ray_distances(origin, direction, tab, max_dist, out):
    """``WallSet.ray_distance`` (slab test) for rays ``origin, direction [N,2]`` into ``out [N]``."""
    for p in range(origin.shape[0]):
        out[p] = _ray_distance(origin[p, 0], origin[p, 1], direction[p, 0], direction[p, 1], tab, tab.shape[1],
                               max_dist)


@njit(cache=True, nogil=True)
def pose_clearance(x, y, yaw, pts_local, grasp_local, tab, carrier_radius):
    """``reference.start_clearance``: formation clearance of the payload pose ``(x, y, yaw)``
    with the carriers on their grasps (payload boundary points, carrier discs vs the walls)."""
    c = math.cos(yaw)
    s = math.sin(yaw)
    buf = np.empty(tab.shape[1])
    pay = np.inf
    for p in range(pts_local.shape[0]):
        _wall_sd(x + (c * pts_local[p, 0] - s * pts_local[p, 1]), y + (s * pts_local[p, 0] + c * pts_local[p, 1]),
                 tab, tab.shape[1], buf)
        for w in range(buf.shape[0]):
            pay = min(pay, buf[w])
    car = np.inf
    for i in range(grasp_local.shape[0]):
        _wall_sd(x + (c * grasp_local[i, 0] - s * grasp_local[i, 1]),
                 y + (s * grasp_local[i, 0] + c * grasp_local[i, 1]), tab, tab.shape[1], buf)
        for w in range(buf.shape[0]):
            car = min(car, buf[w])
    return min(pay, car - carrier_radius)


# ----------------------------------------------------------------------------- route

@njit(cache=True, inline="always")
def _route_project(points, s_table, ds, x, y, s_prev, back, width):
    """``Route.project`` of one point: arc length of the nearest route sample in the window of
    ``width`` samples from ``s_prev - back`` (the first minimum wins)."""
    n = points.shape[0]
    lo = int(min(max(np.rint((s_prev - back) / ds), 0.0), n - 1.0))
    best = np.inf
    bi = 0
    for j in range(width):
        i = min(lo + j, n - 1)
        dx = points[i, 0] - x
        dy = points[i, 1] - y
        d2 = dx * dx + dy * dy
        if d2 < best:
            best = d2
            bi = i
    return s_table[bi]


@njit(cache=True, nogil=True)
def route_project(points, s_table, ds, xy, s_prev, back, width, out):
    """``Route.project``: nearest route sample to ``xy [K,2]`` in the window from ``s_prev - back``."""
    for k in range(xy.shape[0]):
        out[k] = _route_project(points, s_table, ds, xy[k, 0], xy[k, 1], s_prev[k], back, width)


# ----------------------------------------------------------------------------- safety rows

ROWS_NONFINITE, ROWS_COINCIDE = 1, 2   # safety_rows' failure codes


@njit(cache=True, inline="always")
def _insert_sorted(keys, idx, n, key, item):
    """Insert ``(key, item)`` into the first ``n`` sorted entries, after equal keys (stable)."""
    j = n
    while j > 0 and keys[j - 1] > key:
        keys[j] = keys[j - 1]
        idx[j] = idx[j - 1]
        j -= 1
    keys[j] = key
    idx[j] = item


@njit(cache=True, inline="always")
def _wall_h(px, py, tab, nw, margin, out):
    """``safety.point_box_distance``'s signed distance of a point to the first ``nw`` walls, minus
    ``margin``, into ``out[:nw]``."""
    for w in range(nw):
        lx, ly = _box_local(px, py, tab, w)
        hx, hy = tab[2, w], tab[3, w]
        dfx = lx - min(max(lx, -hx), hx)
        dfy = ly - min(max(ly, -hy), hy)
        dout = math.sqrt(dfx * dfx + dfy * dfy)
        inside = -min(hx - abs(lx), hy - abs(ly))   # on or inside: depth to the nearest face
        out[w] = (dout if dout != 0.0 else inside) - margin


@njit(cache=True, inline="always")
def _wall_normal(px, py, tab, w):
    """``safety.point_box_distance``'s outward unit normal (world frame) of wall ``w`` at a point:
    ``(p - q)/|p - q|`` outside, the nearest face's inside or on the boundary (ties to the x-face)."""
    lx, ly = _box_local(px, py, tab, w)
    hx, hy = tab[2, w], tab[3, w]
    dfx = lx - min(max(lx, -hx), hx)
    dfy = ly - min(max(ly, -hy), hy)
    dout = math.sqrt(dfx * dfx + dfy * dfy)
    nlx, nly = 0.0, 0.0
    if dout == 0.0:
        if hx - abs(lx) <= hy - abs(ly):
            nlx = 1.0 if lx >= 0.0 else -1.0
        else:
            nly = 1.0 if ly >= 0.0 else -1.0
    else:
        nlx, nly = dfx / dout, dfy / dout
    c, s = tab[4, w], tab[5, w]
    return c * nlx + (-s) * nly, s * nlx + c * nly


@njit(cache=True, nogil=True)
def _wall_rows(k, pts, B, tab, nw, widx, margin, take, budget, alpha, search_radius, row0,
               C, c, mask, h_out, ent_out, wall_out, sd_buf, near_h, near_w, cand_key, cand_idx):
    """Wall rows of one kind for env ``k`` (see ``reference._wall_rows``), written to rows
    ``row0:row0+budget`` of the outputs (which come zeroed: padding). ``pts [E,2]``, ``B [E,2,9]``;
    the walls are the first ``nw`` of ``tab``, wall ``widx[w]`` of the scene.

    Only candidates with ``h <= search_radius`` are kept: the reference's others have an
    infinite key, sort after them and are masked rows, i.e. padding, whichever wall they name.
    So walls no entity can have within the radius may be left out of ``tab``, and normals are
    computed for the kept rows only."""
    E = pts.shape[0]
    take = min(take, nw)
    if budget == 0 or take == 0 or E == 0:
        return
    n_kept = min(budget, E * take)
    n_cand = 0
    for e in range(E):
        h = sd_buf[e]
        _wall_h(pts[e, 0], pts[e, 1], tab, nw, margin, h)
        # the entity's `take` smallest-h walls (stable), of those within the search radius
        m = 0
        for w in range(nw):
            hv = h[w]
            if hv <= search_radius:
                if m < take:
                    _insert_sorted(near_h, near_w, m, hv, w)
                    m += 1
                elif hv < near_h[take - 1]:
                    _insert_sorted(near_h, near_w, take - 1, hv, w)
        # the kind's n_kept smallest-h candidates, stably sorted: a full buffer takes only keys
        # below its last (equal keys come after it)
        for t in range(m):
            if n_cand < n_kept:
                _insert_sorted(cand_key, cand_idx, n_cand, near_h[t], e * nw + near_w[t])
                n_cand += 1
            elif near_h[t] < cand_key[n_kept - 1]:
                _insert_sorted(cand_key, cand_idx, n_kept - 1, near_h[t], e * nw + near_w[t])
    for r in range(n_cand):
        e = cand_idx[r] // nw
        w = cand_idx[r] % nw
        row = row0 + r
        nx, ny = _wall_normal(pts[e, 0], pts[e, 1], tab, w)
        big = 0.0
        for b in range(C.shape[2]):
            v = nx * B[e, 0, b] + ny * B[e, 1, b]
            C[k, row, b] = v
            big = max(big, abs(v))
        if big > _EPS:
            hv = sd_buf[e, w]
            mask[k, row] = True
            c[k, row] = -alpha * hv
            h_out[k, row] = hv
            ent_out[k, row] = e
            wall_out[k, row] = widx[w]
        else:
            for b in range(C.shape[2]):
                C[k, row, b] = 0.0


@njit(cache=True, nogil=True)
def safety_rows(carrier_xy, carrier_yaw, payload_xy, payload_yaw, pts_local, grasp_local, pair_rest,
                tabs, max_step_xy, alpha, carrier_radius, payload_margin, grasp_tol, search_radius,
                walls_per_carrier, walls_per_point, carrier_budget, payload_budget, formation_budget,
                C, c, mask, h_out, ent_out, wall_out):
    """``reference.build_rows`` per env. ``tabs [Kw,6,W]``: wall tables, ``Kw`` 1 (shared) or K.
    ``formation_budget`` is 6 (the ``"grasp"`` profile's formation rows, after the wall rows) or 0.
    Fills the outputs (padding: zero rows, masked, ``h = 0``, entity and wall -1; formation rows
    name their pair). Returns 0, or ``ROWS_NONFINITE`` if some env's state is not finite, ``ROWS_COINCIDE`` if some
    env's grasp points coincide (the rotation fit is undefined)."""
    K = carrier_xy.shape[0]
    P = pts_local.shape[0]
    W = tabs.shape[2]
    D = C.shape[2]
    cB = np.zeros((3, 2, D))
    pB = np.zeros((P, 2, D))
    pw = np.empty((P, 2))
    g = np.empty((3, 2))
    thB = np.zeros(D)
    tB = np.zeros((2, D))
    all_walls = np.arange(W)
    ptab = np.empty((6, W))          # the walls of the payload pass, and their scene indices
    pidx = np.empty(W, np.int64)
    reach = _reach(pts_local)        # payload points' distance bound from the payload origin
    nmax = max(3, P)
    sd_buf = np.empty((nmax, W))
    near_h = np.empty(max(walls_per_carrier, walls_per_point) + 1)
    near_w = np.empty(near_h.shape[0], np.int64)
    cand_key = np.empty(nmax * near_h.shape[0])
    cand_idx = np.empty(cand_key.shape[0], np.int64)
    pair_i = (0, 0, 1)
    pair_k = (1, 2, 2)
    C[:] = 0.0
    c[:] = 0.0
    mask[:] = False
    h_out[:] = 0.0
    ent_out[:] = -1
    wall_out[:] = -1
    for q in range(formation_budget):   # formation slots name their pair: 0, 0, 1, 1, 2, 2
        ent_out[:, carrier_budget + payload_budget + q] = q // 2
    for k in range(K):
        finite = np.isfinite(payload_xy[k, 0]) and np.isfinite(payload_xy[k, 1]) and np.isfinite(payload_yaw[k])
        for i in range(3):
            finite = (finite and np.isfinite(carrier_xy[k, i, 0]) and np.isfinite(carrier_xy[k, i, 1])
                      and np.isfinite(carrier_yaw[k, i]))
        if not finite:
            return ROWS_NONFINITE
        tab = tabs[0 if tabs.shape[0] == 1 else k]
        # carrier displacement per action: max_step_xy R(psi_i) on columns 3i, 3i+1
        for i in range(3):
            co = math.cos(carrier_yaw[k, i])
            si = math.sin(carrier_yaw[k, i])
            cB[i, 0, 3 * i] = max_step_xy * co
            cB[i, 0, 3 * i + 1] = max_step_xy * -si
            cB[i, 1, 3 * i] = max_step_xy * si
            cB[i, 1, 3 * i + 1] = max_step_xy * co
        cp = math.cos(payload_yaw[k])
        sp = math.sin(payload_yaw[k])
        for i in range(3):
            g[i, 0] = payload_xy[k, 0] + (cp * grasp_local[i, 0] + -sp * grasp_local[i, 1])
            g[i, 1] = payload_xy[k, 1] + (sp * grasp_local[i, 0] + cp * grasp_local[i, 1])
        gm0 = (g[0, 0] + g[1, 0] + g[2, 0]) / 3
        gm1 = (g[0, 1] + g[1, 1] + g[2, 1]) / 3
        S = 0.0
        for i in range(3):
            r0 = g[i, 0] - gm0
            r1 = g[i, 1] - gm1
            S += r0 * r0
            S += r1 * r1
        if S <= _EPS:
            return ROWS_COINCIDE
        # rigid fit: δθ = Σ (J r_i)·d_i / Σ|r_i|², J r = (-r1, r0)
        for i in range(3):
            r0 = g[i, 0] - gm0
            r1 = g[i, 1] - gm1
            for j in range(2):
                b = 3 * i + j
                thB[b] = (-r1 * cB[i, 0, b] + r0 * cB[i, 1, b]) / S
        for i in range(3):   # translation = mean carrier displacement
            for j in range(3):
                b = 3 * i + j
                tB[0, b] = cB[i, 0, b] / 3
                tB[1, b] = cB[i, 1, b] / 3
        for p in range(P):
            pw[p, 0] = payload_xy[k, 0] + (cp * pts_local[p, 0] + -sp * pts_local[p, 1])
            pw[p, 1] = payload_xy[k, 1] + (sp * pts_local[p, 0] + cp * pts_local[p, 1])
            lev0 = -(pw[p, 1] - gm1)
            lev1 = pw[p, 0] - gm0
            for b in range(D):
                pB[p, 0, b] = tB[0, b] + lev0 * thB[b]
                pB[p, 1, b] = tB[1, b] + lev1 * thB[b]
        _wall_rows(k, carrier_xy[k], cB, tab, W, all_walls, carrier_radius, walls_per_carrier, carrier_budget,
                   alpha, search_radius, 0, C, c, mask, h_out, ent_out, wall_out,
                   sd_buf, near_h, near_w, cand_key, cand_idx)
        # payload points can have within search_radius only the walls within search_radius +
        # margin + reach of the payload origin (see _select_walls)
        _wall_sd(payload_xy[k, 0], payload_xy[k, 1], tab, W, sd_buf[0])
        nw = _select_walls(sd_buf[0], search_radius + payload_margin + reach, tab, ptab, pidx)
        _wall_rows(k, pw, pB, ptab, nw, pidx, payload_margin, walls_per_point, payload_budget,
                   alpha, search_radius, carrier_budget, C, c, mask, h_out, ent_out, wall_out,
                   sd_buf, near_h, near_w, cand_key, cand_idx)
        # formation ("grasp" profile only): two rows per pair, linearized along the pair's unit vector
        row0 = carrier_budget + payload_budget
        for q in range(3 if formation_budget > 0 else 0):
            i, kk = pair_i[q], pair_k[q]
            d0 = carrier_xy[k, i, 0] - carrier_xy[k, kk, 0]
            d1 = carrier_xy[k, i, 1] - carrier_xy[k, kk, 1]
            dist = math.sqrt(d0 * d0 + d1 * d1)
            den = dist if dist > _EPS else 1.0
            u0 = d0 / den
            u1 = d1 / den
            big = 0.0
            for b in range(D):
                v = u0 * (cB[i, 0, b] - cB[kk, 0, b]) + u1 * (cB[i, 1, b] - cB[kk, 1, b])
                C[k, row0 + 2 * q, b] = v
                C[k, row0 + 2 * q + 1, b] = -v
                big = max(big, abs(v))
            h_lo = dist - (pair_rest[q] - grasp_tol)
            h_hi = (pair_rest[q] + grasp_tol) - dist
            h_out[k, row0 + 2 * q] = h_lo
            h_out[k, row0 + 2 * q + 1] = h_hi
            if dist > _EPS and big > _EPS:
                mask[k, row0 + 2 * q] = True
                mask[k, row0 + 2 * q + 1] = True
                c[k, row0 + 2 * q] = -alpha * h_lo
                c[k, row0 + 2 * q + 1] = -alpha * h_hi
            else:
                for b in range(D):
                    C[k, row0 + 2 * q, b] = 0.0
                    C[k, row0 + 2 * q + 1, b] = 0.0
        for i in range(3):  # clear this env's carrier columns for the next env
            for a in range(2):
                for j in range(2):
                    cB[i, a, 3 * i + j] = 0.0
    return 0


# ----------------------------------------------------------------------------- physics

@njit(cache=True, inline="always")
def _grasp_strain(px, py, pz, w, ux, uy, uz, gx, gy, cx, cy, hand_z):
    """3-D distance from a hand anchor ``(cx, cy, hand_z)`` to the grasp point ``pos + q ⊗ (g, 0)``."""
    vx, vy, vz = gx, gy, 0.0
    tx = 2.0 * (uy * vz - uz * vy)  # t = 2 u x v
    ty = 2.0 * (uz * vx - ux * vz)
    tz = 2.0 * (ux * vy - uy * vx)
    rx = vx + w * tx + (uy * tz - uz * ty)  # v + w t + u x t
    ry = vy + w * ty + (uz * tx - ux * tz)
    rz = vz + w * tz + (ux * ty - uy * tx)
    dx = (px + rx) - cx
    dy = (py + ry) - cy
    dz = (pz + rz) - hand_z
    return math.sqrt(dx * dx + dy * dy + dz * dz)


@njit(cache=True, nogil=True)
def grasp_strain(payload_pos, payload_quat, grasp_local, carrier_xy, hand_z, out):
    """``reference.grasp_strain``: ``out [K,3]`` = 3-D distance from each carrier's
    hand anchor ``(x, y, hand_z)`` to its grasp point ``pos + q ⊗ (g, 0)`` on the payload."""
    for k in range(payload_pos.shape[0]):
        for i in range(grasp_local.shape[0]):
            out[k, i] = _grasp_strain(payload_pos[k, 0], payload_pos[k, 1], payload_pos[k, 2],
                                      payload_quat[k, 0], payload_quat[k, 1], payload_quat[k, 2], payload_quat[k, 3],
                                      grasp_local[i, 0], grasp_local[i, 1], carrier_xy[k, i, 0], carrier_xy[k, i, 1],
                                      hand_z)


@njit(cache=True, nogil=True)
def reset_states(envs, reset_row, state, qpos, ctrl, eq_active, payload_qadr, carrier_qadr, xy, yaw, pose,
                 carry_height):
    """``reference.physics_reset``: the state rows of envs ``envs`` become ``reset_row``
    (mj_resetData's state), then the payload at ``(xy[j], carry_height)`` with yaw ``yaw[j]``, the
    carriers and their targets at ``pose [n,9]``, grasps on (``qpos``, ``ctrl``, ``eq_active``: views
    of ``state``)."""
    a = payload_qadr
    for j in range(envs.shape[0]):
        k = envs[j]
        state[k, :] = reset_row
        qpos[k, a] = xy[j, 0]
        qpos[k, a + 1] = xy[j, 1]
        qpos[k, a + 2] = carry_height
        qpos[k, a + 3] = math.cos(yaw[j] / 2)
        qpos[k, a + 4] = 0.0
        qpos[k, a + 5] = 0.0
        qpos[k, a + 6] = math.sin(yaw[j] / 2)
        for i in range(carrier_qadr.shape[0]):
            for ax in range(3):
                qpos[k, carrier_qadr[i, ax]] = pose[j, 3 * i + ax]
                ctrl[k, 3 * i + ax] = pose[j, 3 * i + ax]
        eq_active[k, :] = 1.0


@njit(cache=True, nogil=True)
def tracker_targets(qpos, carrier_qadr, actions, max_step_xy, max_step_yaw, leash_xy, leash_yaw, ctrl):
    """``reference.tracker_targets`` in place: ``ctrl [K,9]`` (carrier i's x, y, yaw at
    ``3i..3i+2``) becomes the new tracker targets for actions ``[K,9]`` at the pose in ``qpos``."""
    for k in range(ctrl.shape[0]):
        for i in range(carrier_qadr.shape[0]):
            x = qpos[k, carrier_qadr[i, 0]]
            y = qpos[k, carrier_qadr[i, 1]]
            yaw = qpos[k, carrier_qadr[i, 2]]
            ax = min(max(actions[k, 3 * i], -1.0), 1.0)
            ay = min(max(actions[k, 3 * i + 1], -1.0), 1.0)
            az = min(max(actions[k, 3 * i + 2], -1.0), 1.0)
            c = math.cos(yaw)
            s = math.sin(yaw)
            ctrl[k, 3 * i] = min(max(ctrl[k, 3 * i], x - leash_xy), x + leash_xy) + (c * ax - s * ay) * max_step_xy
            ctrl[k, 3 * i + 1] = (min(max(ctrl[k, 3 * i + 1], y - leash_xy), y + leash_xy)
                                  + (s * ax + c * ay) * max_step_xy)
            ctrl[k, 3 * i + 2] = min(max(ctrl[k, 3 * i + 2], yaw - leash_yaw), yaw + leash_yaw) + az * max_step_yaw


# ----------------------------------------------------------------------------- task view

@njit(cache=True, inline="always")
def _wrap(a):
    """``geometry.wrap``: angle wrapped to [-pi, pi)."""
    return (a + math.pi) % (2 * math.pi) - math.pi


@njit(cache=True, inline="always")
def _route_index(s, ds, n):
    """``Route.index``: nearest route sample of arc length ``s``."""
    return int(min(max(np.rint(s / ds), 0.0), n - 1.0))


@njit(cache=True, nogil=True)
def place_episodes(envs, start, goal_s, route_points, route_heading, route_n, route_ds, grasp_local, facing, goal_xy,
                   goal_yaw, carriers):
    """``reference.place_episodes``: rows ``envs`` of ``goal_xy``, ``goal_yaw`` (the route
    pose at ``goal_s``) and ``carriers [n,3,3]`` (envs' carriers on the grasps of ``start [K,3]``).
    Env k's route is the first ``route_n[k]`` samples of ``route_points[k]``, ``route_heading[k]``
    (``scene.SceneBatch``), ``route_ds[k]`` apart."""
    for j in range(envs.shape[0]):
        k = envs[j]
        x, y, yaw = start[k, 0], start[k, 1], start[k, 2]
        c = math.cos(yaw)
        s = math.sin(yaw)
        for i in range(grasp_local.shape[0]):
            carriers[j, i, 0] = x + (c * grasp_local[i, 0] - s * grasp_local[i, 1])
            carriers[j, i, 1] = y + (s * grasp_local[i, 0] + c * grasp_local[i, 1])
            carriers[j, i, 2] = yaw + facing[i]
        ig = _route_index(goal_s[k], route_ds[k], route_n[k])
        goal_xy[k, 0] = route_points[k, ig, 0]
        goal_xy[k, 1] = route_points[k, ig, 1]
        goal_yaw[k] = route_heading[k, ig]


@njit(cache=True, nogil=True)
def snapshot_rows(envs, qpos, qvel, contact, carrier_qadr, carrier_vadr, payload_qadr, payload_vadr,
                  route_points, route_s, route_heading, route_n, route_ds, back, route_width, s_prev, goal_s,
                  lookahead, tabs, pts_local, grasp_local, hand_z, carrier_radius,
                  cxy, cyaw, cvel, pxy, pz, pyaw, tilt, pvel, strain, s_out, look_xy, look_yaw, route_yaw,
                  contact_out, clearance, pay_dist, pay_vec, car_dist):
    """``reference.snapshot`` for envs ``envs``, written to rows ``envs`` of the snapshot
    fields (the arguments after ``carrier_radius``). Env k's scene (``scene.SceneBatch``): walls
    ``tabs[k]`` and route the first ``route_n[k]`` samples of ``route_points[k]`` (``route_s[k]``,
    ``route_heading[k]``, ``route_ds[k]`` apart); ``back``, ``route_width[k]``: ``Route.project``'s window."""
    W = tabs.shape[2]
    buf = np.empty(W)
    near, near_idx = np.empty((6, W)), np.empty(W, np.int64)
    reach = _reach(pts_local)
    for j in range(envs.shape[0]):
        k = envs[j]
        tab = tabs[k]
        n_route, ds = route_n[k], route_ds[k]
        points, s_table, heading = route_points[k, :n_route], route_s[k, :n_route], route_heading[k, :n_route]
        for i in range(3):
            cxy[k, i, 0] = qpos[k, carrier_qadr[i, 0]]
            cxy[k, i, 1] = qpos[k, carrier_qadr[i, 1]]
            cyaw[k, i] = qpos[k, carrier_qadr[i, 2]]
            for a in range(3):
                cvel[k, i, a] = qvel[k, carrier_vadr[i, a]]
        for a in range(6):
            pvel[k, a] = qvel[k, payload_vadr + a]
        px = qpos[k, payload_qadr]
        py = qpos[k, payload_qadr + 1]
        qw = qpos[k, payload_qadr + 3]   # the payload's quaternion (w, x, y, z)
        qx = qpos[k, payload_qadr + 4]
        qy = qpos[k, payload_qadr + 5]
        qz = qpos[k, payload_qadr + 6]
        yaw = math.atan2(2 * (qw * qz + qx * qy), 1 - 2 * (qy * qy + qz * qz))  # physics.quat_to_yaw_tilt
        zz = 1 - 2 * (qx * qx + qy * qy)
        pxy[k, 0] = px
        pxy[k, 1] = py
        pz[k] = qpos[k, payload_qadr + 2]
        pyaw[k] = yaw
        tilt[k] = math.acos(min(max(zz, -1.0), 1.0))
        for i in range(3):
            strain[k, i] = _grasp_strain(px, py, pz[k], qw, qx, qy, qz, grasp_local[i, 0], grasp_local[i, 1],
                                         cxy[k, i, 0], cxy[k, i, 1], hand_z)
        s = _route_project(points, s_table, ds, px, py, s_prev[k], back, route_width[k])
        s_out[k] = s
        il = _route_index(min(s + lookahead, goal_s[k]), ds, n_route)
        look_xy[k, 0] = points[il, 0]
        look_xy[k, 1] = points[il, 1]
        look_yaw[k] = heading[il]
        route_yaw[k] = heading[_route_index(s, ds, n_route)]
        contact_out[k] = contact[k]
        c = math.cos(yaw)
        sn = math.sin(yaw)
        _wall_sd(px, py, tab, W, buf)   # the walls that can be some payload point's nearest
        nearest = np.inf
        for w in range(W):
            nearest = min(nearest, buf[w])
        nw = _select_walls(buf, nearest + 2 * reach, tab, near, near_idx)
        pay_min = np.inf
        for p in range(pts_local.shape[0]):
            bx = px + (c * pts_local[p, 0] - sn * pts_local[p, 1])
            by = py + (sn * pts_local[p, 0] + c * pts_local[p, 1])
            pay_dist[k, p], pay_vec[k, p, 0], pay_vec[k, p, 1] = _nearest_wall(bx, by, near, nw, buf)
            pay_min = min(pay_min, pay_dist[k, p])
        car_min = np.inf
        for i in range(3):
            _wall_sd(cxy[k, i, 0], cxy[k, i, 1], tab, W, buf)
            best = np.inf
            for w in range(W):
                best = min(best, buf[w])
            car_dist[k, i] = best
            car_min = min(car_min, best)
        clearance[k] = min(pay_min, car_min - carrier_radius)


@njit(cache=True, inline="always")
def _to_frame(x, y, c, s):
    """``geometry.to_frame`` of one vector: ``R(yaw)^T (x, y)`` with ``c, s = cos, sin(yaw)``."""
    return c * x + s * y, -s * x + c * y


@njit(cache=True, nogil=True)
def observe_rows(envs, cxy, cyaw, cvel, pxy, pz, pyaw, tilt, pvel, strain, look_xy, look_yaw, clearance, pay_dist,
                 pay_vec, goal_xy, goal_yaw, progress, time_left, human_slot, tabs, grasp_local, facing,
                 ray_angles, v_scale, w_scale, lookahead, drop_strain, carrier_radius, ray_max, carry_height,
                 obs, state):
    """``reference.observe`` for envs ``envs``: rows ``envs`` of ``obs [K,3,OBS_DIM]`` and
    ``state [K,STATE_DIM]`` (float32; computed in float64 in the references' order of operations).
    ``human_slot`` is -1 without a human; env k's walls are ``tabs[k]``."""
    W = tabs.shape[2]
    buf = np.empty(W)
    near, near_idx = np.empty((6, W)), np.empty(W, np.int64)
    for j in range(envs.shape[0]):
        k = envs[j]
        tab = tabs[k]
        px, py, yaw = pxy[k, 0], pxy[k, 1], pyaw[k]
        lcos, lsin = math.cos(look_yaw[k]), math.sin(look_yaw[k])
        pcos, psin = math.cos(yaw), math.sin(yaw)
        # nearest payload point to a wall (first minimum, as argmin)
        pbest = 0
        for p in range(1, pay_dist.shape[1]):
            if pay_dist[k, p] < pay_dist[k, pbest]:
                pbest = p
        for i in range(3):
            o = obs[k, i]
            cx, cy, psi = cxy[k, i, 0], cxy[k, i, 1], cyaw[k, i]   # carrier i's pose
            c, s = math.cos(psi), math.sin(psi)
            vx, vy = _to_frame(cvel[k, i, 0], cvel[k, i, 1], c, s)
            o[0] = vx / v_scale
            o[1] = vy / v_scale
            o[2] = cvel[k, i, 2] / w_scale
            gx, gy = grasp_local[i, 0], grasp_local[i, 1]
            sx = look_xy[k, 0] + (lcos * gx - lsin * gy) - cx   # own grasp slot at the lookahead pose
            sy = look_xy[k, 1] + (lsin * gx + lcos * gy) - cy
            fx, fy = _to_frame(sx, sy, c, s)
            o[3] = fx / lookahead
            o[4] = fy / lookahead
            o[5] = _wrap(look_yaw[k] + facing[i] - psi)
            fx, fy = _to_frame(px + (pcos * gx - psin * gy) - cx, py + (psin * gx + pcos * gy) - cy, c, s)
            o[6] = fx / drop_strain
            o[7] = fy / drop_strain
            o[8] = strain[k, i] / drop_strain
            fx, fy = _to_frame(px - cx, py - cy, c, s)
            o[9] = fx
            o[10] = fy
            o[11] = math.sin(yaw - psi)
            o[12] = math.cos(yaw - psi)
            o[13] = _wrap(look_yaw[k] - yaw)
            fx, fy = _to_frame(look_xy[k, 0] - px, look_xy[k, 1] - py, c, s)
            o[14] = fx / lookahead
            o[15] = fy / lookahead
            fx, fy = _to_frame(goal_xy[k, 0] - px, goal_xy[k, 1] - py, c, s)
            o[16] = min(max(fx / 5.0, -2.0), 2.0)
            o[17] = min(max(fy / 5.0, -2.0), 2.0)
            o[18] = _wrap(goal_yaw[k] - yaw)
            o[19] = progress[k]
            for off in range(1, 3):
                m = (i + off) % 3
                fx, fy = _to_frame(cxy[k, m, 0] - cx, cxy[k, m, 1] - cy, c, s)
                o[20 + 3 * (off - 1)] = fx / 2.0
                o[21 + 3 * (off - 1)] = fy / 2.0
                o[22 + 3 * (off - 1)] = strain[k, m] / drop_strain
            _wall_sd(cx, cy, tab, W, buf)   # walls farther than a ray's length cannot cut it
            nw = _select_walls(buf, ray_max + carrier_radius, tab, near, near_idx)
            for r in range(4):
                ry = psi + ray_angles[r]
                ray = _ray_distance(cx, cy, math.cos(ry), math.sin(ry), near, nw, ray_max + carrier_radius) \
                    - carrier_radius
                o[26 + r] = min(max(ray, -carrier_radius), ray_max) / ray_max
                state[k, 38 + 4 * i + r] = o[26 + r]
            o[30] = min(pay_dist[k, pbest], 2.0)
            fx, fy = _to_frame(pay_vec[k, pbest, 0], pay_vec[k, pbest, 1], c, s)
            o[31] = fx
            o[32] = fy
            o[33] = time_left[k]
        # the centralized critic's state, in the payload frame
        st = state[k]
        st[0] = px / 10.0
        st[1] = py / 10.0
        st[2] = pcos
        st[3] = psin
        fx, fy = _to_frame(pvel[k, 0], pvel[k, 1], pcos, psin)
        st[4] = fx / v_scale
        st[5] = fy / v_scale
        st[6] = pvel[k, 5] / w_scale
        st[7] = (pz[k] - carry_height) / 0.1
        st[8] = tilt[k] * 10.0
        for i in range(3):
            fx, fy = _to_frame(cxy[k, i, 0] - px, cxy[k, i, 1] - py, pcos, psin)
            st[9 + 2 * i] = (fx - grasp_local[i, 0]) / drop_strain
            st[10 + 2 * i] = (fy - grasp_local[i, 1]) / drop_strain
            st[15 + i] = _wrap(cyaw[k, i] - yaw - facing[i])
            fx, fy = _to_frame(cvel[k, i, 0], cvel[k, i, 1], pcos, psin)
            st[18 + 2 * i] = fx / v_scale
            st[19 + 2 * i] = fy / v_scale
            st[24 + i] = cvel[k, i, 2] / w_scale
            st[34 + i] = strain[k, i] / drop_strain
            st[51 + i] = 1.0 if i == human_slot else 0.0
        fx, fy = _to_frame(look_xy[k, 0] - px, look_xy[k, 1] - py, pcos, psin)
        st[27] = fx / lookahead
        st[28] = fy / lookahead
        st[29] = _wrap(look_yaw[k] - yaw)
        fx, fy = _to_frame(goal_xy[k, 0] - px, goal_xy[k, 1] - py, pcos, psin)
        st[30] = min(max(fx / 5.0, -2.0), 2.0)
        st[31] = min(max(fy / 5.0, -2.0), 2.0)
        st[32] = _wrap(goal_yaw[k] - yaw)
        st[33] = progress[k]
        st[37] = min(clearance[k], 2.0)
        st[50] = time_left[k]


@njit(cache=True, nogil=True)
def step_outcome_rows(strain, pxy, pyaw, route_yaw, s, contact, s_old, t, max_steps, goal_xy, goal_yaw,
                      drop_strain, goal_pos_tol, goal_yaw_tol, max_step_xy, w_progress, w_heading, w_strain,
                      w_collision, w_drop, w_time, w_success, reward, success, drop, terminated, truncated,
                      heading_err):
    """``reference.step_outcome`` for all K envs, into the [K] outputs (the arguments after ``w_success``)."""
    for k in range(strain.shape[0]):
        dr = max(strain[k, 0], strain[k, 1], strain[k, 2]) > drop_strain
        dx = pxy[k, 0] - goal_xy[k, 0]
        dy = pxy[k, 1] - goal_xy[k, 1]
        ok = math.sqrt(dx * dx + dy * dy) < goal_pos_tol and abs(_wrap(pyaw[k] - goal_yaw[k])) < goal_yaw_tol
        su = ok and not dr
        drop[k] = dr
        success[k] = su
        terminated[k] = dr or su
        truncated[k] = t[k] >= max_steps and not (dr or su)
        he = abs(_wrap(route_yaw[k] - pyaw[k]))
        heading_err[k] = he
        ds = min(max(s[k] - s_old[k], -2 * max_step_xy), 2 * max_step_xy)
        q0 = strain[k, 0] / drop_strain
        q1 = strain[k, 1] / drop_strain
        q2 = strain[k, 2] / drop_strain
        reward[k] = (w_progress * ds / max_step_xy - w_heading * he - w_strain * ((q0 * q0 + q1 * q1 + q2 * q2) / 3)
                     - w_collision * contact[k] - w_drop * dr - w_time + w_success * su)


@njit(cache=True, nogil=True)
def accumulate_episodes(acc, min_clear, reward, collision, margin_violation, tilt, heading_err, pz, clearance,
                        carry_height):
    """``reference.accumulate``: add one step to the per-episode sums ``acc [6,K]``
    (return, collision steps, margin-violation steps, tilt in degrees, heading error, height
    error) and the running minimum clearance."""
    for k in range(acc.shape[1]):
        acc[0, k] += reward[k]
        acc[1, k] += collision[k]
        acc[2, k] += margin_violation[k]
        acc[3, k] += tilt[k] * (180.0 / math.pi)
        acc[4, k] += heading_err[k]
        acc[5, k] += abs(pz[k] - carry_height)
        min_clear[k] = min(min_clear[k], clearance[k])


@njit(cache=True, nogil=True)
def add_noise(envs, block, used, std, obs):
    """``obs[k] += block[k, used[k]] * std`` and ``used[k] += 1`` for k in ``envs`` (float32, the
    arithmetic of ``obs + noise * std``): each env's next observation-noise draw."""
    for j in range(envs.shape[0]):
        k = envs[j]
        noise = block[k, used[k]]
        for i in range(obs.shape[1]):
            for f in range(obs.shape[2]):
                obs[k, i, f] += noise[i, f] * std[f]
        used[k] += 1


# ----------------------------------------------------------------------------- margins

@njit(cache=True, nogil=True)
def spec_barrier_min(carrier_sd, payload_sd, carrier_xy, pair_rest, carrier_radius, payload_margin, grasp_tol,
                     formation, out):
    """``reference.spec_barrier_min`` into ``out [K]``; ``formation``: include the pair band."""
    pair_i = (0, 0, 1)
    pair_k = (1, 2, 2)
    for k in range(out.shape[0]):
        h = np.inf
        if carrier_sd.shape[1]:
            m = np.inf
            for i in range(carrier_sd.shape[1]):
                m = min(m, carrier_sd[k, i])
            h = min(h, m - carrier_radius)
        if payload_sd.shape[1]:
            m = np.inf
            for p in range(payload_sd.shape[1]):
                m = min(m, payload_sd[k, p])
            h = min(h, m - payload_margin)
        if formation:
            m = np.inf
            for q in range(3):
                d0 = carrier_xy[k, pair_i[q], 0] - carrier_xy[k, pair_k[q], 0]
                d1 = carrier_xy[k, pair_i[q], 1] - carrier_xy[k, pair_k[q], 1]
                m = min(m, grasp_tol - abs(math.sqrt(d0 * d0 + d1 * d1) - pair_rest[q]))
            h = min(h, m)
        out[k] = h
