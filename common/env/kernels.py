"""Numba kernels for the per-step geometry of the environment (the hot path of ``BatchEnv.step``).

Each kernel is a loop-over-envs version of a numpy reference that stays in the
owning module (``safety.build_rows_reference``, ``geometry.WallSet`` methods,
``scenarios.Route.project``); tests/test_env_fast.py checks them against those
references. The arithmetic follows the references operation by operation
(same products, same summation order, same tie-breaking: the first minimum
wins, sorts are stable) so results agree to rounding and discrete choices
(nearest wall, kept rows) agree exactly.
"""
from __future__ import annotations

import math

import numpy as np
from numba import njit

_EPS = 1e-12


# ----------------------------------------------------------------------------- point–box queries

@njit(cache=True, inline="always")
def _box_local(px, py, wall, c, s):
    """``R(yaw)^T (p - centre)`` of a point in a wall box's frame."""
    dx = px - wall[0]
    dy = py - wall[1]
    return c * dx + s * dy, -s * dx + c * dy


@njit(cache=True, inline="always")
def _box_sd(lx, ly, hx, hy):
    """Signed distance of a local point to the box ``[-hx, hx] x [-hy, hy]``."""
    qx = abs(lx) - hx
    qy = abs(ly) - hy
    ox = max(qx, 0.0)
    oy = max(qy, 0.0)
    return math.sqrt(ox * ox + oy * oy) + min(max(qx, qy), 0.0)


@njit(cache=True)
def signed_distances(pts, walls, cos, sin, out):
    """``WallSet.signed_distance`` for points ``[N,2]`` into ``out [N,W]``."""
    for p in range(pts.shape[0]):
        for w in range(walls.shape[0]):
            lx, ly = _box_local(pts[p, 0], pts[p, 1], walls[w], cos[w], sin[w])
            out[p, w] = _box_sd(lx, ly, walls[w, 2], walls[w, 3])


@njit(cache=True)
def nearest_walls(pts, walls, cos, sin, dist, vec):
    """``WallSet.nearest`` for points ``[N,2]``: fills ``dist [N]`` and ``vec [N,2]``."""
    for p in range(pts.shape[0]):
        best = np.inf
        bdx = 0.0
        bdy = 0.0
        bw = 0
        for w in range(walls.shape[0]):
            lx, ly = _box_local(pts[p, 0], pts[p, 1], walls[w], cos[w], sin[w])
            d = _box_sd(lx, ly, walls[w, 2], walls[w, 3])
            if d < best:  # first minimum wins, like argmin
                best = d
                bw = w
                bdx = min(max(lx, -walls[w, 2]), walls[w, 2]) - lx
                bdy = min(max(ly, -walls[w, 3]), walls[w, 3]) - ly
        dist[p] = best
        vec[p, 0] = cos[bw] * bdx - sin[bw] * bdy
        vec[p, 1] = sin[bw] * bdx + cos[bw] * bdy


@njit(cache=True)
def ray_distances(origin, direction, walls, cos, sin, max_dist, out):
    """``WallSet.ray_distance`` (slab test) for rays ``origin, direction [N,2]`` into ``out [N]``."""
    for p in range(origin.shape[0]):
        ux, uy = direction[p, 0], direction[p, 1]
        best = np.inf
        for w in range(walls.shape[0]):
            lx, ly = _box_local(origin[p, 0], origin[p, 1], walls[w], cos[w], sin[w])
            dx = cos[w] * ux + sin[w] * uy
            dy = -sin[w] * ux + cos[w] * uy
            ix = 1.0 / (1e-12 if abs(dx) < 1e-12 else dx)
            iy = 1.0 / (1e-12 if abs(dy) < 1e-12 else dy)
            hx, hy = walls[w, 2], walls[w, 3]
            t1x = (-hx - lx) * ix
            t2x = (hx - lx) * ix
            t1y = (-hy - ly) * iy
            t2y = (hy - ly) * iy
            tmin = max(min(t1x, t2x), min(t1y, t2y))
            tmax = min(max(t1x, t2x), max(t1y, t2y))
            t0 = max(tmin, 0.0)
            best = min(best, t0 if tmax >= t0 else max_dist)
        out[p] = min(best, max_dist)


# ----------------------------------------------------------------------------- route

@njit(cache=True)
def route_project(points, s_table, ds, xy, s_prev, back, width, out):
    """``Route.project``: nearest route sample to ``xy [K,2]`` in the window from ``s_prev - back``."""
    n = points.shape[0]
    for k in range(xy.shape[0]):
        lo = int(min(max(np.rint((s_prev[k] - back) / ds), 0.0), n - 1.0))
        best = np.inf
        bi = 0
        for j in range(width):
            i = min(lo + j, n - 1)
            dx = points[i, 0] - xy[k, 0]
            dy = points[i, 1] - xy[k, 1]
            d2 = dx * dx + dy * dy
            if d2 < best:
                best = d2
                bi = i
        out[k] = s_table[bi]


# ----------------------------------------------------------------------------- safety rows

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


@njit(cache=True)
def _wall_rows(k, pts, B, walls, cw, sw, margin, take, budget, alpha, search_radius, row0,
               C, c, mask, h_out, ent_out, wall_out, sd_buf, n_buf, near_h, near_w, cand_key, cand_idx):
    """Wall rows of one kind for env ``k`` (see ``safety._wall_rows_reference``), written to rows
    ``row0:row0+budget`` of the outputs. ``pts [E,2]``, ``B [E,2,9]``."""
    E = pts.shape[0]
    W = walls.shape[0]
    take = min(take, W)
    if budget == 0 or take == 0 or E == 0:
        return
    for e in range(E):
        px, py = pts[e, 0], pts[e, 1]
        for w in range(W):
            lx, ly = _box_local(px, py, walls[w], cw[w], sw[w])
            hx, hy = walls[w, 2], walls[w, 3]
            clx = min(max(lx, -hx), hx)
            cly = min(max(ly, -hy), hy)
            dfx = lx - clx
            dfy = ly - cly
            dout = math.sqrt(dfx * dfx + dfy * dfy)
            if dout == 0.0:  # on or inside: nearest face (ties to the x-face)
                sx = 1.0 if lx >= 0.0 else -1.0
                sy = 1.0 if ly >= 0.0 else -1.0
                depx = hx - abs(lx)
                depy = hy - abs(ly)
                if depx <= depy:
                    nlx, nly = sx, 0.0
                else:
                    nlx, nly = 0.0, sy
                sd = -min(depx, depy)
            else:
                nlx, nly = dfx / dout, dfy / dout
                sd = dout
            sd_buf[e, w] = sd - margin
            n_buf[e, w, 0] = cw[w] * nlx + (-sw[w]) * nly
            n_buf[e, w, 1] = sw[w] * nlx + cw[w] * nly
        # per entity: its `take` smallest-h walls (stable)
        m = 0
        for w in range(W):
            hv = sd_buf[e, w]
            if m < take:
                _insert_sorted(near_h, near_w, m, hv, w)
                m += 1
            elif hv < near_h[take - 1]:
                _insert_sorted(near_h, near_w, take - 1, hv, w)
        # candidates of the kind, keyed by h (inf beyond the search radius), stably sorted
        for t in range(take):
            hv = near_h[t]
            key = hv if hv <= search_radius else np.inf
            _insert_sorted(cand_key, cand_idx, e * take + t, key, e * W + near_w[t])
    n_kept = min(budget, E * take)
    for r in range(n_kept):
        key = cand_key[r]
        e = cand_idx[r] // W
        w = cand_idx[r] % W
        row = row0 + r
        big = 0.0
        for b in range(C.shape[2]):
            v = n_buf[e, w, 0] * B[e, 0, b] + n_buf[e, w, 1] * B[e, 1, b]
            C[k, row, b] = v
            big = max(big, abs(v))
        if np.isfinite(key) and big > _EPS:
            hv = sd_buf[e, w]
            mask[k, row] = True
            c[k, row] = -alpha * hv
            h_out[k, row] = hv
            ent_out[k, row] = e
            wall_out[k, row] = w
        else:
            for b in range(C.shape[2]):
                C[k, row, b] = 0.0


@njit(cache=True)
def safety_rows(carrier_xy, carrier_yaw, payload_xy, payload_yaw, pts_local, grasp_local, pair_rest,
                walls, max_step_xy, alpha, carrier_radius, payload_margin, grasp_tol, search_radius,
                walls_per_carrier, walls_per_point, carrier_budget, payload_budget, formation_budget,
                C, c, mask, h_out, ent_out, wall_out):
    """``safety.build_rows_reference`` per env. ``walls [Kw,W,5]`` with ``Kw`` 1 (shared) or K.
    ``formation_budget`` is 6 (the ``"grasp"`` profile's formation rows, after the wall rows) or 0.
    Outputs must come zeroed (``ent_out``/``wall_out`` filled with -1, formation ``ent_out`` set).
    Returns False if some env's grasp points coincide (the rotation fit is undefined)."""
    K = carrier_xy.shape[0]
    P = pts_local.shape[0]
    W = walls.shape[1]
    D = C.shape[2]
    cB = np.zeros((3, 2, D))
    pB = np.zeros((P, 2, D))
    pw = np.empty((P, 2))
    g = np.empty((3, 2))
    thB = np.zeros(D)
    cw = np.empty(W)
    sw = np.empty(W)
    nmax = max(3, P)
    sd_buf = np.empty((nmax, W))
    n_buf = np.empty((nmax, W, 2))
    near_h = np.empty(max(walls_per_carrier, walls_per_point) + 1)
    near_w = np.empty(near_h.shape[0], np.int64)
    cand_key = np.empty(nmax * near_h.shape[0])
    cand_idx = np.empty(cand_key.shape[0], np.int64)
    pair_i = (0, 0, 1)
    pair_k = (1, 2, 2)
    for k in range(K):
        kw = k if walls.shape[0] > 1 else 0
        for w in range(W):
            cw[w] = math.cos(walls[kw, w, 4])
            sw[w] = math.sin(walls[kw, w, 4])
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
            return False
        # rigid fit: δθ = Σ (J r_i)·d_i / Σ|r_i|², J r = (-r1, r0)
        for i in range(3):
            r0 = g[i, 0] - gm0
            r1 = g[i, 1] - gm1
            for j in range(2):
                b = 3 * i + j
                thB[b] = (-r1 * cB[i, 0, b] + r0 * cB[i, 1, b]) / S
        for p in range(P):
            pw[p, 0] = payload_xy[k, 0] + (cp * pts_local[p, 0] + -sp * pts_local[p, 1])
            pw[p, 1] = payload_xy[k, 1] + (sp * pts_local[p, 0] + cp * pts_local[p, 1])
            lev0 = -(pw[p, 1] - gm1)
            lev1 = pw[p, 0] - gm0
            for i in range(3):
                for j in range(3):
                    b = 3 * i + j
                    pB[p, 0, b] = cB[i, 0, b] / 3 + lev0 * thB[b]
                    pB[p, 1, b] = cB[i, 1, b] / 3 + lev1 * thB[b]
        _wall_rows(k, carrier_xy[k], cB, walls[kw], cw, sw, carrier_radius, walls_per_carrier, carrier_budget,
                   alpha, search_radius, 0, C, c, mask, h_out, ent_out, wall_out,
                   sd_buf, n_buf, near_h, near_w, cand_key, cand_idx)
        _wall_rows(k, pw, pB, walls[kw], cw, sw, payload_margin, walls_per_point, payload_budget,
                   alpha, search_radius, carrier_budget, C, c, mask, h_out, ent_out, wall_out,
                   sd_buf, n_buf, near_h, near_w, cand_key, cand_idx)
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
    return True


# ----------------------------------------------------------------------------- physics

@njit(cache=True)
def grasp_strain(payload_pos, payload_quat, grasp_local, carrier_xy, hand_z, out):
    """``TransportPhysics.grasp_strain_reference``: ``out [K,3]`` = 3-D distance from each carrier's
    hand anchor ``(x, y, hand_z)`` to its grasp point ``pos + q ⊗ (g, 0)`` on the payload."""
    for k in range(payload_pos.shape[0]):
        w, ux, uy, uz = payload_quat[k, 0], payload_quat[k, 1], payload_quat[k, 2], payload_quat[k, 3]
        for i in range(grasp_local.shape[0]):
            vx, vy, vz = grasp_local[i, 0], grasp_local[i, 1], 0.0
            tx = 2.0 * (uy * vz - uz * vy)  # t = 2 u x v
            ty = 2.0 * (uz * vx - ux * vz)
            tz = 2.0 * (ux * vy - uy * vx)
            rx = vx + w * tx + (uy * tz - uz * ty)  # v + w t + u x t
            ry = vy + w * ty + (uz * tx - ux * tz)
            rz = vz + w * tz + (ux * ty - uy * tx)
            dx = (payload_pos[k, 0] + rx) - carrier_xy[k, i, 0]
            dy = (payload_pos[k, 1] + ry) - carrier_xy[k, i, 1]
            dz = (payload_pos[k, 2] + rz) - hand_z
            out[k, i] = math.sqrt(dx * dx + dy * dy + dz * dz)
