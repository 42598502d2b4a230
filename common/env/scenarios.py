"""The nine transport scenarios as small declarative descriptions.

A ``ScenarioSpec`` lists static walls (2-D oriented boxes ``(cx, cy, hx, hy, yaw)``,
all tall), a reference route of payload-centre waypoints, the start randomization
ranges and the goal range; ``common/env/mjcf.py`` builds the MuJoCo model from it and
``Route`` turns the waypoints into a dense arc-length table with reference headings.

Families (paper Sec. IV-A): LCP local clearance and passage, STR sequential turning
and reorientation, CCN constrained corridor navigation. The formation footprint
(board plus carrier discs) is 2.1 m x 1.05 m, so gates of 1.35-1.45 m leave
0.15-0.2 m per side and need the payload aligned (Needle) or rotated (Tilt) to pass.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from common.env.layout import CARRIER_RADIUS, GRASP_LOCAL, PAYLOAD_HALF
from common.env.layout import FOOTPRINT_SHIFT as S

WALL_T = 0.2        # wall thickness
WALL_HEIGHT = 1.6   # walls are taller than the payload


@dataclass(frozen=True)
class ScenarioSpec:
    name: str
    title: str
    family: str
    walls: tuple[tuple[float, float, float, float, float], ...]
    route: tuple[tuple[float, float], ...]   # payload-centre waypoints; start = first, farthest goal = last
    start_range: tuple[float, float, float] = (0.2, 0.3, 0.25)  # +- x, y (m) and yaw (rad) around route start
    goal_range: float = 0.6                  # goal arc length drawn from [S_end - goal_range, S_end]
    max_steps: int = 300
    bounds: tuple[float, float, float, float] = (0.0, 10.0, -2.0, 2.0)  # plot extent

    def walls_array(self) -> np.ndarray:
        return np.asarray(self.walls, dtype=np.float64).reshape(-1, 5)


# --- wall builders -----------------------------------------------------------------

def _segment_wall(p0, p1, extend0=0.0, extend1=0.0, t=WALL_T, side=0.0):
    """Box along segment p0->p1, lengthened by extend at each end, shifted sideways by side."""
    p0, p1 = np.asarray(p0, float), np.asarray(p1, float)
    u = (p1 - p0) / np.linalg.norm(p1 - p0)
    n = np.array([-u[1], u[0]])
    a, b = p0 - extend0 * u + side * n, p1 + extend1 * u + side * n
    c = 0.5 * (a + b)
    return (float(c[0]), float(c[1]), float(0.5 * np.linalg.norm(b - a)), t / 2, math.atan2(u[1], u[0]))


def _rect(x0, x1, y0, y1):
    """Axis-aligned solid block."""
    return ((x0 + x1) / 2, (y0 + y1) / 2, (x1 - x0) / 2, (y1 - y0) / 2, 0.0)


def _room(x0, x1, y0, y1):
    """Four walls whose inner faces bound the rectangle [x0,x1] x [y0,y1]."""
    t = WALL_T
    return (
        _rect(x0 - t, x1 + t, y1, y1 + t), _rect(x0 - t, x1 + t, y0 - t, y0),
        _rect(x0 - t, x0, y0, y1), _rect(x1, x1 + t, y0, y1),
    )


def _gate(x, y0, y1, centre, opening, t=WALL_T):
    """Wall across a corridor at x (from y0 to y1) with an opening around `centre`."""
    lo, hi = centre - opening / 2, centre + opening / 2
    return (_rect(x - t / 2, x + t / 2, y0, lo), _rect(x - t / 2, x + t / 2, hi, y1))


def _corridor(centerline, width):
    """Walls of a polyline corridor with inner faces at +-width/2, closed at both ends."""
    pts = np.asarray(centerline, float)
    half, t = width / 2, WALL_T
    walls = []
    dirs = [(pts[k + 1] - pts[k]) / np.linalg.norm(pts[k + 1] - pts[k]) for k in range(len(pts) - 1)]
    for sign in (+1.0, -1.0):  # +1 left wall, -1 right wall
        # miter offset polyline of this side (inner face), then boxes outside it
        off = []
        for k in range(len(pts)):
            if k == 0 or k == len(pts) - 1:
                u = dirs[0] if k == 0 else dirs[-1]
                off.append(pts[k] + sign * half * np.array([-u[1], u[0]]))
                continue
            u0, u1 = dirs[k - 1], dirs[k]
            n0, n1 = np.array([-u0[1], u0[0]]), np.array([-u1[1], u1[0]])
            m = n0 + n1
            off.append(pts[k] + sign * half * m / np.dot(m, n0))
        for k in range(len(pts) - 1):
            # an outer corner for this side needs the wall lengthened to close the joint
            def outer(j):
                if j == 0 or j == len(pts) - 1:
                    return True
                cross = dirs[j - 1][0] * dirs[j][1] - dirs[j - 1][1] * dirs[j][0]
                return sign * cross < 0  # right turn is outer for the left wall
            walls.append(_segment_wall(off[k], off[k + 1], t if outer(k) else 0.0,
                                       t if outer(k + 1) else 0.0, side=sign * t / 2))
    for k, u in ((0, -dirs[0]), (len(pts) - 1, dirs[-1])):  # end caps
        n = np.array([-u[1], u[0]])
        c = pts[k] + u * t / 2
        walls.append(_segment_wall(c - n * (half + t), c + n * (half + t)))
    return tuple(walls)


def _tilt_gate():
    # a diagonal wall (45 deg) across the corridor with an aperture that only fits the
    # footprint when the payload crosses perpendicular to the wall (heading -45 deg)
    y0, y1, opening = -2.2, 2.2, 1.4
    g = np.array([5.0, 0.0])
    w = np.array([1.0, 1.0]) / math.sqrt(2)   # wall direction
    n = np.array([1.0, -1.0]) / math.sqrt(2)  # crossing direction
    a, b = g + w * (y0 - g[1]) / w[1], g + w * (y1 - g[1]) / w[1]
    gc = g + w * S  # footprint centred in the aperture: payload centre shifted left of n
    walls = _room(0.0, 10.0, y0, y1) + (
        _segment_wall(a, g - w * opening / 2),
        _segment_wall(g + w * opening / 2, b),
    )

    def on_line(y):  # route point on the crossing line at height y
        t = (y - gc[1]) / n[1]
        return (float(gc[0] + t * n[0]), y)

    route = ((1.3, 1.3), on_line(1.3), on_line(-1.3), (8.7, -1.3))
    return walls, route


_tilt_walls, _tilt_route = _tilt_gate()

_SPECS = [
    ScenarioSpec(
        "narrow_gate", "Narrow Gate", "LCP",
        walls=_room(0.0, 10.0, -1.5, 1.5) + _gate(5.0, -1.5, 1.5, 0.0, 1.45),
        route=((1.3, S), (8.7, S)),
        start_range=(0.2, 0.35, 0.25), max_steps=220, bounds=(-0.3, 10.3, -1.8, 1.8),
    ),
    ScenarioSpec(
        "needle_gate", "Needle Gate", "LCP",
        # a 1.5 m deep channel of 1.35 m: the payload must enter aligned and stay aligned
        walls=_room(0.0, 10.5, -1.6, 1.6) + (_rect(4.5, 6.0, -1.6, -0.675), _rect(4.5, 6.0, 0.675, 1.6)),
        route=((1.3, S), (9.2, S)),
        start_range=(0.2, 0.35, 0.45), max_steps=240, bounds=(-0.3, 10.8, -1.9, 1.9),
    ),
    ScenarioSpec(
        "tilt_gate", "Tilt Gate", "LCP",
        walls=_tilt_walls, route=_tilt_route,
        start_range=(0.2, 0.25, 0.25), max_steps=260, bounds=(-0.3, 10.3, -2.5, 2.5),
    ),
    ScenarioSpec(
        "double_gate", "Double Gate", "STR",
        walls=_room(0.0, 11.8, -1.7, 1.7) + _gate(3.5, -1.7, 1.7, 0.6, 1.45) + _gate(8.6, -1.7, 1.7, -0.6, 1.45),
        route=((1.3, 0.6 + S), (5.4, 0.6 + S), (6.6, -0.6 + S), (10.6, -0.6 + S)),
        start_range=(0.15, 0.2, 0.2), max_steps=300, bounds=(-0.3, 12.1, -2.0, 2.0),
    ),
    ScenarioSpec(
        "chicane", "Chicane", "STR",
        walls=_room(0.0, 12.6, -2.0, 2.0) + (_rect(2.6, 3.6, -2.0, 0.2), _rect(9.0, 10.0, -0.2, 2.0)),
        route=((1.3, 1.1 + S), (5.5, 1.1 + S), (7.5, -1.1 + S), (11.3, -1.1 + S)),
        start_range=(0.15, 0.2, 0.2), max_steps=320, bounds=(-0.3, 12.9, -2.3, 2.3),
    ),
    ScenarioSpec(
        "s_corridor", "S-Shaped Corridor", "STR",
        walls=_corridor([(0.0, 0.0), (4.6, 0.0), (4.6, 3.2), (0.6, 3.2), (0.6, 6.4), (5.2, 6.4)], 2.3),
        route=((1.3, 0.0), (4.6, 0.0), (4.6, 3.2), (0.6, 3.2), (0.6, 6.4), (4.0, 6.4)),
        start_range=(0.15, 0.2, 0.2), max_steps=450, bounds=(-1.6, 6.7, -1.6, 8.0),
    ),
    ScenarioSpec(
        "l_corridor", "L-Corridor", "CCN",
        walls=_corridor([(0.0, 0.0), (5.5, 0.0), (5.5, 5.6)], 2.3),
        route=((1.3, 0.0), (5.5, 0.0), (5.5, 4.4)),
        start_range=(0.2, 0.25, 0.25), max_steps=300, bounds=(-0.5, 7.0, -1.6, 6.0),
    ),
    ScenarioSpec(
        "u_corridor", "U-Shaped Corridor", "CCN",
        walls=_corridor([(0.0, 0.0), (5.5, 0.0), (5.5, 3.5), (0.0, 3.5)], 2.3),
        route=((1.3, 0.0), (5.5, 0.0), (5.5, 3.5), (1.3, 3.5)),
        start_range=(0.2, 0.25, 0.25), max_steps=380, bounds=(-0.5, 7.0, -1.6, 5.1),
    ),
    ScenarioSpec(
        "maze", "Maze", "CCN",
        walls=_corridor([(0.0, 0.0), (4.2, 0.0), (4.2, 3.5), (8.2, 3.5), (8.2, 0.0), (12.4, 0.0)], 2.3),
        route=((1.3, 0.0), (4.2, 0.0), (4.2, 3.5), (8.2, 3.5), (8.2, 0.0), (11.2, 0.0)),
        start_range=(0.15, 0.2, 0.2), max_steps=450, bounds=(-0.5, 12.9, -1.6, 5.1),
    ),
]

SCENARIOS: dict[str, ScenarioSpec] = {s.name: s for s in _SPECS}
FAMILIES: dict[str, list[str]] = {
    fam: [s.name for s in _SPECS if s.family == fam] for fam in ("LCP", "STR", "CCN")
}
SCENARIO_TITLES: dict[str, str] = {s.name: s.title for s in _SPECS}


class Route:
    """Dense arc-length table of a scenario route: points, tangents and reference headings.

    The reference heading is the segment tangent, blended linearly over +-``blend`` metres
    of arc length around each interior waypoint so the payload turns while it rounds a
    corner instead of at the corner.
    """

    def __init__(self, waypoints, ds: float = 0.05, blend: float = 0.7):
        wp = np.asarray(waypoints, dtype=np.float64)
        if wp.ndim != 2 or wp.shape[1] != 2 or len(wp) < 2:
            raise ValueError("route needs at least two (x, y) waypoints")
        seg = np.diff(wp, axis=0)
        seg_len = np.linalg.norm(seg, axis=1)
        if np.any(seg_len < 1e-6):
            raise ValueError("route has repeated waypoints")
        knots = np.concatenate([[0.0], np.cumsum(seg_len)])
        self.length = float(knots[-1])
        n = int(math.ceil(self.length / ds)) + 1
        self.s = np.linspace(0.0, self.length, n)
        self.ds = self.s[1] - self.s[0]
        self.points = np.stack([np.interp(self.s, knots, wp[:, 0]), np.interp(self.s, knots, wp[:, 1])], axis=1)
        seg_heading = np.unwrap(np.arctan2(seg[:, 1], seg[:, 0]))
        hs, hv = [0.0], [seg_heading[0]]
        for k in range(1, len(wp) - 1):
            b = min(blend, 0.45 * seg_len[k - 1], 0.45 * seg_len[k])
            hs += [knots[k] - b, knots[k] + b]
            hv += [seg_heading[k - 1], seg_heading[k]]
        hs.append(self.length)
        hv.append(seg_heading[-1])
        self.heading = np.interp(self.s, hs, hv)  # unwrapped
        seg_idx = np.clip(np.searchsorted(knots, self.s, side="right") - 1, 0, len(seg) - 1)
        self.tangent = seg[seg_idx] / seg_len[seg_idx, None]

    def index(self, s):
        return np.clip(np.rint(np.asarray(s) / self.ds).astype(np.int64), 0, len(self.s) - 1)

    def pose(self, s):
        """Route point [...,2] and reference heading [...] at arc length s (nearest sample)."""
        i = self.index(s)
        return self.points[i], self.heading[i]

    def project(self, xy, s_prev, back: float = 0.6, ahead: float = 1.6):
        """Arc length of the route point nearest to xy [K,2], searched near s_prev [K].

        The window keeps the projection on the current corridor run where the route
        folds back on itself (U, S, maze).
        """
        from common.env.kernels import route_project

        xy = np.ascontiguousarray(xy, dtype=np.float64)
        s_prev = np.ascontiguousarray(np.broadcast_to(np.asarray(s_prev, np.float64), (len(xy),)))
        out = np.empty(len(xy))
        width = int(math.ceil((back + ahead) / self.ds)) + 1
        route_project(self.points, self.s, float(self.ds), xy, s_prev, float(back), width, out)
        return out

    def project_reference(self, xy, s_prev, back: float = 0.6, ahead: float = 1.6):
        """Numpy :meth:`project` (the reference its numba kernel is tested against)."""
        lo = self.index(np.asarray(s_prev) - back)
        width = int(math.ceil((back + ahead) / self.ds)) + 1
        idx = np.minimum(lo[:, None] + np.arange(width)[None, :], len(self.s) - 1)
        d2 = np.sum((self.points[idx] - xy[:, None, :]) ** 2, axis=-1)
        return self.s[idx[np.arange(len(xy)), np.argmin(d2, axis=1)]]


def formation_footprint(xy, yaw, n_arc: int = 8):
    """World points of the formation outline (board boundary and carrier discs) at poses [K]."""
    hx, hy = PAYLOAD_HALF[0], PAYLOAD_HALF[1]
    t = np.linspace(-1, 1, 9)
    board = np.concatenate([
        np.stack([t * hx, np.full_like(t, hy)], 1), np.stack([t * hx, np.full_like(t, -hy)], 1),
        np.stack([np.full_like(t, hx), t * hy], 1), np.stack([np.full_like(t, -hx), t * hy], 1)])
    ang = np.linspace(0, 2 * math.pi, n_arc, endpoint=False)
    disc = np.stack([np.cos(ang), np.sin(ang)], 1) * CARRIER_RADIUS
    local = np.concatenate([board] + [g + disc for g in GRASP_LOCAL])
    c, s = np.cos(yaw)[:, None], np.sin(yaw)[:, None]
    return np.stack([xy[:, None, 0] + c * local[:, 0] - s * local[:, 1],
                     xy[:, None, 1] + s * local[:, 0] + c * local[:, 1]], axis=-1)
