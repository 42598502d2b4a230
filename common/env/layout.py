"""Physical layout of the three-carrier team and its payload (constants, defined once).

Physical layout (payload frame, x along the long axis, metres):

* payload: a ``1.6 x 0.8 x 0.04`` board of ``10 kg`` carried at ``0.8 m``;
* carrier 0 grasps the front short-end midpoint ``(+0.8, 0)``, carrier 1 the back
  short-end midpoint ``(-0.8, 0)``, carrier 2 the right long-edge midpoint ``(0, -0.4)``
  (three non-collinear grasps);
* each carrier is a planar holonomic base (slide x, slide y, hinge yaw) of radius
  ``0.25 m`` whose grasp anchor lies on its yaw axis, facing the payload centre.
"""
from __future__ import annotations

import math

import numpy as np

PAYLOAD_HALF = (0.8, 0.4, 0.02)  # board half-sizes (x, y, z)
PAYLOAD_MASS = 10.0
CARRY_HEIGHT = 0.8
CARRIER_RADIUS = 0.25
# grasp points in the payload frame; carrier i holds GRASP_LOCAL[i]
GRASP_LOCAL = np.array([[0.8, 0.0], [-0.8, 0.0], [0.0, -0.4]])
# carrier yaw relative to the payload when in formation: each faces the payload centre
FACING = np.array([math.pi, 0.0, math.pi / 2])
# Spacing of the payload boundary points. A wall corner can slip between two
# points by at most half the spacing (90-degree corner), so the spacing must stay
# below 2 * SafetyConfig.payload_margin (0.05 m) for the payload-wall rows to
# keep thin gate posts out of the board's edges. With the first sampling
# (corners and edge midpoints, 0.8 m apart) a 0.2 m gate post passed between
# the points and shielded policies scraped the payload along it.
PAYLOAD_POINT_SPACING = 0.08


def perimeter_points(half_x: float, half_y: float, spacing: float) -> np.ndarray:
    """Points around a rectangle's boundary, corners included, at most ``spacing`` apart."""
    corners = np.array([[half_x, half_y], [-half_x, half_y], [-half_x, -half_y], [half_x, -half_y]])
    pts = []
    for a, b in zip(corners, np.roll(corners, -1, axis=0)):
        n = max(1, int(math.ceil(np.linalg.norm(b - a) / spacing - 1e-9)))
        pts += [a + (b - a) * t for t in np.arange(n) / n]
    return np.array(pts)


# payload boundary points for clearance and safety rows
PAYLOAD_POINTS_LOCAL = perimeter_points(0.8, 0.4, PAYLOAD_POINT_SPACING)
# pairs (0,1), (0,2), (1,2) as in common/env/safety.py
PAIRS = ((0, 1), (0, 2), (1, 2))
PAIR_REST = np.array([np.linalg.norm(GRASP_LOCAL[i] - GRASP_LOCAL[j]) for i, j in PAIRS])
# the formation footprint (board + carrier discs) is centred at y = -0.125 in the payload
# frame; scenario routes pass gates with this lateral shift so the footprint is centred
FOOTPRINT_SHIFT = 0.125
