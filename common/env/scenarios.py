"""The nine transport scenarios as small declarative descriptions, each a family of layouts.

A ``ScenarioSpec`` names its layout parameters (``LayoutParam``: a nominal value and the
half-width of a uniform per-episode draw, in metres or degrees) and a layout builder, a
function of those parameters that returns static walls (2-D oriented boxes ``(cx, cy, hx,
hy, yaw)``, all tall) and a reference route of payload-centre waypoints. The builder's
docstring is the scenario's: it states each spread and the physical grounds for it (what
rooms and placements of this kind vary by). :func:`draw_layout` is the one draw, a pure
function ``(spec, rng, spread) -> Layout``; ``spread=0`` is the nominal layout, which is
also ``spec.walls`` / ``spec.route``. Every draw of a scenario has the same number of walls
(the MuJoCo model is compiled once and its wall geoms moved per episode, see
``common/env/physics.py``). ``common/env/mjcf.py`` builds the MuJoCo model and ``Route``
turns the waypoints into a dense arc-length table with reference headings.

Families (paper Sec. IV-A): LCP local clearance and passage, STR sequential turning
and reorientation, CCN constrained corridor navigation. The formation footprint
(board plus carrier discs) is 2.1 m x 1.05 m, so gates of 1.35-1.45 m leave
0.15-0.2 m per side and need the payload aligned (Needle) or rotated (Tilt) to pass.
"""
from __future__ import annotations

import functools
import math
from dataclasses import dataclass
from typing import Callable, Mapping

import numpy as np

from common.env.layout import CARRIER_RADIUS, GRASP_LOCAL, PAYLOAD_HALF
from common.env.layout import FOOTPRINT_SHIFT as S

WALL_T = 0.2        # wall thickness
WALL_HEIGHT = 1.6   # walls are taller than the payload


@dataclass(frozen=True)
class LayoutParam:
    """One layout parameter: drawn uniformly from ``nominal +- spread * half_range`` per episode."""

    name: str
    nominal: float
    half_range: float   # >= 0, in ``unit``
    unit: str           # "m" or "deg"


@dataclass(frozen=True)
class Layout:
    """A concrete layout: walls ``[W,5]``, route waypoints ``[R,2]`` and the parameter values drawn."""

    walls: np.ndarray
    route: np.ndarray
    params: Mapping[str, float]


@dataclass(frozen=True)
class ScenarioSpec:
    name: str
    title: str
    family: str
    build: Callable[[Mapping[str, float]], tuple]   # params -> (walls, route); docstring = the spreads' grounds
    params: tuple[LayoutParam, ...]
    start_range: tuple[float, float, float] = (0.2, 0.3, 0.25)  # +- x, y (m) and yaw (rad) around route start
    goal_range: float = 0.6                  # goal arc length drawn from [S_end - goal_range, S_end]
    max_steps: int = 300
    bounds: tuple[float, float, float, float] = (0.0, 10.0, -2.0, 2.0)  # plot extent of the nominal layout

    @functools.cached_property
    def nominal(self) -> Layout:
        return draw_layout(self, None, 0.0)

    @property
    def walls(self) -> tuple:
        """The nominal layout's walls (tuples ``(cx, cy, hx, hy, yaw)``)."""
        return tuple(tuple(float(v) for v in w) for w in self.nominal.walls)

    @property
    def route(self) -> tuple:
        """The nominal layout's route waypoints."""
        return tuple(tuple(float(v) for v in p) for p in self.nominal.route)

    def walls_array(self) -> np.ndarray:
        return self.nominal.walls.copy()


def draw_layout(spec: ScenarioSpec, rng: np.random.Generator | None, spread: float = 1.0) -> Layout:
    """A layout of ``spec``: every parameter uniform in ``nominal +- spread * half_range``, drawn
    from ``rng`` in the order of ``spec.params`` (one ``rng.uniform`` call); ``spread=0`` (or
    ``rng=None``) is the nominal layout. Pure: the same rng state gives the same layout."""
    if not (np.isfinite(spread) and spread >= 0):
        raise ValueError(f"layout spread must be finite and >= 0, got {spread!r}")
    nominal = np.array([p.nominal for p in spec.params])
    half = np.array([p.half_range for p in spec.params]) * spread
    values = nominal if rng is None or spread == 0 else nominal + half * rng.uniform(-1.0, 1.0, len(nominal))
    params = {p.name: float(v) for p, v in zip(spec.params, values)}
    walls, route = spec.build(params)
    # rounded to 1e-12 (m, rad): trigonometry's last bits would otherwise move a nominal route's
    # length across a sample boundary (cos(90 deg) = 6e-17)
    walls = np.round(np.asarray(walls, dtype=np.float64).reshape(-1, 5), 12)
    route = np.round(np.asarray(route, dtype=np.float64).reshape(-1, 2), 12)
    if np.any(walls[:, 2:4] <= 0):
        raise ValueError(f"{spec.name}: a drawn wall has a non-positive half-size (spread too wide): {params}")
    return Layout(walls=walls, route=route, params=params)


# --- wall builders -----------------------------------------------------------------

def _segment_wall(p0, p1, extend0=0.0, extend1=0.0, t=WALL_T, side=0.0):
    """Box along segment p0->p1, lengthened by extend at each end, shifted sideways by side.
    (Scalar arithmetic: layouts are built at every episode reset.)"""
    x0, y0, x1, y1 = float(p0[0]), float(p0[1]), float(p1[0]), float(p1[1])
    length = math.hypot(x1 - x0, y1 - y0)
    ux, uy = (x1 - x0) / length, (y1 - y0) / length
    cx = 0.5 * (x0 + x1) + 0.5 * (extend1 - extend0) * ux - side * uy
    cy = 0.5 * (y0 + y1) + 0.5 * (extend1 - extend0) * uy + side * ux
    return (cx, cy, 0.5 * (length + extend0 + extend1), t / 2, math.atan2(uy, ux))


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
    pts = [(float(x), float(y)) for x, y in centerline]
    half, t, n_pts = width / 2, WALL_T, len(pts)
    dirs = []
    for (xa, ya), (xb, yb) in zip(pts[:-1], pts[1:]):
        d = math.hypot(xb - xa, yb - ya)
        dirs.append(((xb - xa) / d, (yb - ya) / d))
    walls = []
    for sign in (+1.0, -1.0):  # +1 left wall, -1 right wall
        # miter offset polyline of this side (inner face), then boxes outside it
        off = []
        for k, (x, y) in enumerate(pts):
            if k == 0 or k == n_pts - 1:
                ux, uy = dirs[0] if k == 0 else dirs[-1]
                off.append((x - sign * half * uy, y + sign * half * ux))
                continue
            (u0x, u0y), (u1x, u1y) = dirs[k - 1], dirs[k]
            mx, my = -u0y - u1y, u0x + u1x              # n0 + n1 (left normals)
            scale = sign * half / (mx * -u0y + my * u0x)  # / (m . n0)
            off.append((x + scale * mx, y + scale * my))

        def outer(j):
            # an outer corner for this side needs the wall lengthened to close the joint
            if j == 0 or j == n_pts - 1:
                return True
            cross = dirs[j - 1][0] * dirs[j][1] - dirs[j - 1][1] * dirs[j][0]
            return sign * cross < 0  # right turn is outer for the left wall

        for k in range(n_pts - 1):
            walls.append(_segment_wall(off[k], off[k + 1], t if outer(k) else 0.0,
                                       t if outer(k + 1) else 0.0, side=sign * t / 2))
    for k, (ux, uy) in ((0, (-dirs[0][0], -dirs[0][1])), (n_pts - 1, dirs[-1])):  # end caps
        nx, ny = -uy, ux
        cx, cy = pts[k][0] + ux * t / 2, pts[k][1] + uy * t / 2
        r = half + t
        walls.append(_segment_wall((cx - nx * r, cy - ny * r), (cx + nx * r, cy + ny * r)))
    return tuple(walls)


# --- layouts: one builder per scenario --------------------------------------------------
# Spreads are half-ranges of uniform draws at layout_spread = 1 (EnvConfig). Shared grounds:
# rooms and corridors built to one plan differ by decimetres (wall finishes, shelving, columns),
# openings of one nominal door size by centimetres (frames, hinges), and a door or turn sits where
# the building allows, within about half a metre of where a plan would put it. Start and goal marks
# are taped by hand. The within-room start jitter (start_range x EnvConfig.start_spread) comes on top.

def _p(name, nominal, half_range, unit="m"):
    return LayoutParam(name, float(nominal), float(half_range), unit)


def _narrow_gate(p):
    """Narrow Gate: a 10 m x 3 m hall crossed by a partition with one 1.45 m door.

    Spreads: hall length +-0.5 m, half-width +-0.1 m (halls of one plan, a shelf or finish
    either side); door position along the hall +-0.5 m and across it +-0.25 m (a partition
    door is placed where the structure allows); clear opening +-0.04 m (double-door sets of
    one nominal size, 1.41-1.49 m, by frame and hinge); start and goal marks +-0.2 m across
    the hall (taped by hand). The route runs straight through the door, 1.2 m either side.
    """
    L, hw, gx, gc = p["length"], p["half_width"], p["gate_x"], p["gate_y"]
    walls = _room(0.0, L, -hw, hw) + _gate(gx, -hw, hw, gc, p["opening"])
    route = ((1.3, p["start_y"] + S), (gx - 1.2, gc + S), (gx + 1.2, gc + S), (L - 1.3, p["goal_y"] + S))
    return walls, route


def _needle_gate(p):
    """Needle Gate: a 10.5 m x 3.2 m hall with a 1.5 m deep, 1.35 m wide passage.

    Spreads: hall length +-0.5 m, half-width +-0.1 m; passage entry along the hall +-0.5 m
    and across it +-0.15 m; depth +-0.3 m (a doorway through a 1.2-1.8 m service wall or a
    rack end); clear width +-0.03 m only (1.32-1.38 m: 0.13-0.17 m per side of the 1.05 m
    footprint, so the passage keeps demanding an aligned payload, which is what it tests);
    start and goal marks +-0.2 m across the hall.
    """
    L, hw, cx, cy, d, w = p["length"], p["half_width"], p["entry_x"], p["channel_y"], p["depth"], p["width"]
    walls = _room(0.0, L, -hw, hw) + (_rect(cx, cx + d, -hw, cy - w / 2), _rect(cx, cx + d, cy + w / 2, hw))
    route = ((1.3, p["start_y"] + S), (cx - 1.2, cy + S), (cx + d + 1.2, cy + S), (L - 1.3, p["goal_y"] + S))
    return walls, route


def _tilt_gate(p):
    """Tilt Gate: a 10 m x 4.4 m hall crossed by a diagonal (45 deg) wall whose 1.4 m aperture
    fits the footprint only when the payload crosses perpendicular to the wall.

    Spreads: wall angle +-5 deg (a diagonal partition set out by hand between two columns);
    aperture centre along the hall +-0.4 m and across it +-0.15 m; aperture +-0.04 m (door
    sets, as Narrow Gate); half-width +-0.1 m; start and goal marks +-0.15 m across the hall.
    """
    hw, op = p["half_width"], p["opening"]
    y0, y1 = -hw, hw
    th = math.radians(p["wall_angle"])
    g = np.array([p["gate_x"], p["gate_y"]])
    w = np.array([math.cos(th), math.sin(th)])    # wall direction
    n = np.array([math.sin(th), -math.cos(th)])   # crossing direction
    a, b = g + w * (y0 - g[1]) / w[1], g + w * (y1 - g[1]) / w[1]
    gc = g + w * S  # footprint centred in the aperture: payload centre shifted left of n
    walls = _room(0.0, 10.0, y0, y1) + (_segment_wall(a, g - w * op / 2), _segment_wall(g + w * op / 2, b))

    def on_line(y):  # route point on the crossing line at height y
        t = (y - gc[1]) / n[1]
        return (float(gc[0] + t * n[0]), y)

    route = ((1.3, 1.3 + p["start_y"]), on_line(1.3), on_line(-1.3), (8.7, -1.3 + p["goal_y"]))
    return walls, route


def _double_gate(p):
    """Double Gate: an 11.8 m x 3.4 m hall with two 1.45 m doors 5.1 m apart, offset +-0.6 m
    across it, so the payload crosses over between them.

    Spreads: first door along the hall +-0.3 m, door spacing +-0.3 m, each door's offset across
    the hall +-0.15 m and clear opening +-0.04 m; exit length after the second door +-0.3 m;
    half-width +-0.1 m; start and goal marks +-0.15 m across the hall. The cross-over keeps
    its 1.2 m run between the doors.
    """
    hw, g1x, g1y, g2y = p["half_width"], p["gate1_x"], p["gate1_y"], p["gate2_y"]
    g2x = g1x + p["spacing"]
    L = g2x + p["exit_length"]
    dm = (p["spacing"] - 5.1) / 2
    walls = (_room(0.0, L, -hw, hw) + _gate(g1x, -hw, hw, g1y, p["opening1"])
             + _gate(g2x, -hw, hw, g2y, p["opening2"]))
    route = ((1.3, g1y + p["start_y"] + S), (g1x + 1.9 + dm, g1y + S), (g2x - 2.0 - dm, g2y + S),
             (L - 1.2, g2y + p["goal_y"] + S))
    return walls, route


def _chicane(p):
    """Chicane: a 12.6 m x 4 m hall with two 1 m deep blocks from opposite walls, leaving a
    1.8 m lane at each; the payload changes lane between them.

    Spreads: first block along the hall +-0.3 m, block spacing +-0.3 m, block depth (along the
    hall) +-0.2 m (pallets, machines or racks of this size), each block's reach across the
    hall +-0.15 m; exit length +-0.3 m; half-width +-0.1 m. The route keeps each lane's middle.
    """
    hw, b1, bw, t1, t2 = p["half_width"], p["block1_x"], p["block_depth"], p["tip1_y"], p["tip2_y"]
    b2 = b1 + p["spacing"]
    L = b2 + p["exit_length"]
    dm = (p["spacing"] - 6.4) / 2
    lane1, lane2 = (t1 + hw) / 2, (t2 - hw) / 2
    walls = _room(0.0, L, -hw, hw) + (_rect(b1, b1 + bw, -hw, t1), _rect(b2, b2 + bw, t2, hw))
    route = ((1.3, lane1 + S), (b1 + bw + 1.9 + dm, lane1 + S), (b2 - 1.5 - dm, lane2 + S), (L - 1.3, lane2 + S))
    return walls, route


_CORRIDOR_GROUNDS = """Corridor spreads: width +-0.08 m (2.22-2.38 m; one corridor plan with different
    finishes, handrails or cable trays), each leg +-0.3-0.4 m and each rise between parallel
    legs +-0.15 m (where the turns fall in a building), start mark along the first leg +-0.15 m
    and goal mark back from the end +-0.3 m (taped by hand)."""


def _s_corridor(p):
    """S-Shaped Corridor: 2.3 m wide, legs 4.6, 3.2, 4.0, 3.2, 4.6 m with four 90 deg turns.

    Spreads: first leg (turn x) +-0.3 m, the middle leg's end (x) +-0.2 m, the last leg's end
    +-0.3 m, rise +-0.15 m; {corridor}
    """
    a, h, b, c = p["turn1_x"], p["rise"], p["turn3_x"], p["end_x"]
    pts = [(0.0, 0.0), (a, 0.0), (a, h), (b, h), (b, 2 * h), (c, 2 * h)]
    route = [(p["start_x"], 0.0)] + pts[1:-1] + [(c - p["goal_back"], 2 * h)]
    return _corridor(pts, p["width"]), tuple(route)


def _l_corridor(p):
    """L-Corridor: 2.3 m wide, legs 5.5 m and 5.6 m with one 90 deg turn.

    Spreads: turn angle +-8 deg (corridors meeting at a column or an older wing are rarely
    square), legs +-0.4 m; {corridor}
    """
    a, l2, th = p["leg1"], p["leg2"], math.radians(p["turn_angle"])
    u = np.array([math.cos(th), math.sin(th)])
    end, goal = np.array([a, 0.0]) + l2 * u, np.array([a, 0.0]) + (l2 - p["goal_back"]) * u
    pts = [(0.0, 0.0), (a, 0.0), tuple(end)]
    return _corridor(pts, p["width"]), ((p["start_x"], 0.0), (a, 0.0), tuple(goal))


def _u_corridor(p):
    """U-Shaped Corridor: 2.3 m wide, legs 5.5, 3.5 and 5.5 m with two 90 deg turns.

    Spreads: legs +-0.4 m, rise +-0.15 m; {corridor}
    """
    a, h, l3 = p["leg1"], p["rise"], p["leg3"]
    pts = [(0.0, 0.0), (a, 0.0), (a, h), (a - l3, h)]
    route = ((p["start_x"], 0.0), (a, 0.0), (a, h), (a - l3 + p["goal_back"], h))
    return _corridor(pts, p["width"]), route


def _maze(p):
    """Maze: 2.3 m wide, legs 4.2, 3.5, 4.0, 3.5, 4.2 m with four 90 deg turns (up, across, down).

    Spreads: the three horizontal legs +-0.3 m, rise +-0.15 m; {corridor}
    """
    a, h, b, c = p["leg1"], p["rise"], p["leg2"], p["leg3"]
    pts = [(0.0, 0.0), (a, 0.0), (a, h), (a + b, h), (a + b, 0.0), (a + b + c, 0.0)]
    route = [(p["start_x"], 0.0)] + pts[1:-1] + [(a + b + c - p["goal_back"], 0.0)]
    return _corridor(pts, p["width"]), tuple(route)


for _fn in (_s_corridor, _l_corridor, _u_corridor, _maze):
    _fn.__doc__ = _fn.__doc__.format(corridor=_CORRIDOR_GROUNDS)

_CORRIDOR_ENDS = (_p("width", 2.3, 0.08), _p("start_x", 1.3, 0.15))

_SPECS = [
    ScenarioSpec(
        "narrow_gate", "Narrow Gate", "LCP", _narrow_gate,
        (_p("length", 10.0, 0.5), _p("half_width", 1.5, 0.1), _p("gate_x", 5.0, 0.5), _p("gate_y", 0.0, 0.25),
         _p("opening", 1.45, 0.04), _p("start_y", 0.0, 0.2), _p("goal_y", 0.0, 0.2)),
        start_range=(0.2, 0.35, 0.25), max_steps=220, bounds=(-0.3, 10.3, -1.8, 1.8),
    ),
    ScenarioSpec(
        "needle_gate", "Needle Gate", "LCP", _needle_gate,
        (_p("length", 10.5, 0.5), _p("half_width", 1.6, 0.1), _p("entry_x", 4.5, 0.5), _p("channel_y", 0.0, 0.15),
         _p("depth", 1.5, 0.3), _p("width", 1.35, 0.03), _p("start_y", 0.0, 0.2), _p("goal_y", 0.0, 0.2)),
        start_range=(0.2, 0.35, 0.45), max_steps=240, bounds=(-0.3, 10.8, -1.9, 1.9),
    ),
    ScenarioSpec(
        "tilt_gate", "Tilt Gate", "LCP", _tilt_gate,
        (_p("half_width", 2.2, 0.1), _p("gate_x", 5.0, 0.4), _p("gate_y", 0.0, 0.15), _p("wall_angle", 45.0, 5.0, "deg"),
         _p("opening", 1.4, 0.04), _p("start_y", 0.0, 0.15), _p("goal_y", 0.0, 0.15)),
        start_range=(0.2, 0.25, 0.25), max_steps=260, bounds=(-0.3, 10.3, -2.5, 2.5),
    ),
    ScenarioSpec(
        "double_gate", "Double Gate", "STR", _double_gate,
        (_p("half_width", 1.7, 0.1), _p("gate1_x", 3.5, 0.3), _p("spacing", 5.1, 0.3), _p("gate1_y", 0.6, 0.15),
         _p("gate2_y", -0.6, 0.15), _p("opening1", 1.45, 0.04), _p("opening2", 1.45, 0.04),
         _p("exit_length", 3.2, 0.3), _p("start_y", 0.0, 0.15), _p("goal_y", 0.0, 0.15)),
        start_range=(0.15, 0.2, 0.2), max_steps=300, bounds=(-0.3, 12.1, -2.0, 2.0),
    ),
    ScenarioSpec(
        "chicane", "Chicane", "STR", _chicane,
        (_p("half_width", 2.0, 0.1), _p("block1_x", 2.6, 0.3), _p("spacing", 6.4, 0.3), _p("block_depth", 1.0, 0.2),
         _p("tip1_y", 0.2, 0.15), _p("tip2_y", -0.2, 0.15), _p("exit_length", 3.6, 0.3)),
        start_range=(0.15, 0.2, 0.2), max_steps=320, bounds=(-0.3, 12.9, -2.3, 2.3),
    ),
    ScenarioSpec(
        "s_corridor", "S-Shaped Corridor", "STR", _s_corridor,
        _CORRIDOR_ENDS + (_p("turn1_x", 4.6, 0.3), _p("rise", 3.2, 0.15), _p("turn3_x", 0.6, 0.2),
                          _p("end_x", 5.2, 0.3), _p("goal_back", 1.2, 0.3)),
        start_range=(0.15, 0.2, 0.2), max_steps=450, bounds=(-1.6, 6.7, -1.6, 8.0),
    ),
    ScenarioSpec(
        "l_corridor", "L-Corridor", "CCN", _l_corridor,
        _CORRIDOR_ENDS + (_p("leg1", 5.5, 0.4), _p("leg2", 5.6, 0.4), _p("turn_angle", 90.0, 8.0, "deg"),
                          _p("goal_back", 1.2, 0.3)),
        start_range=(0.2, 0.25, 0.25), max_steps=300, bounds=(-0.5, 7.0, -1.6, 6.0),
    ),
    ScenarioSpec(
        "u_corridor", "U-Shaped Corridor", "CCN", _u_corridor,
        _CORRIDOR_ENDS + (_p("leg1", 5.5, 0.4), _p("rise", 3.5, 0.15), _p("leg3", 5.5, 0.4), _p("goal_back", 1.3, 0.3)),
        start_range=(0.2, 0.25, 0.25), max_steps=380, bounds=(-0.5, 7.0, -1.6, 5.1),
    ),
    ScenarioSpec(
        "maze", "Maze", "CCN", _maze,
        _CORRIDOR_ENDS + (_p("leg1", 4.2, 0.3), _p("rise", 3.5, 0.15), _p("leg2", 4.0, 0.3), _p("leg3", 4.2, 0.3),
                          _p("goal_back", 1.2, 0.3)),
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
