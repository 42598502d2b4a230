"""The payload boundary points are dense enough that the board cannot overlap
a wall while every point still keeps its margin (a thin gate post slipping
between sparse points made shielded policies scrape walls)."""
import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from common.env.layout import PAYLOAD_HALF, PAYLOAD_POINTS_LOCAL, perimeter_points
from common.env.safety import SafetyConfig, point_box_distance


def _corners(cx, cy, hx, hy, yaw):
    R = np.array([[np.cos(yaw), -np.sin(yaw)], [np.sin(yaw), np.cos(yaw)]])
    local = np.array([[hx, hy], [-hx, hy], [-hx, -hy], [hx, -hy]])
    return local @ R.T + [cx, cy]


def _rectangles_overlap(a, b):
    """Separating-axis test for two convex quadrilaterals (independent of the env code)."""
    for poly in (a, b):
        for i in range(4):
            edge = poly[(i + 1) % 4] - poly[i]
            axis = np.array([-edge[1], edge[0]])
            pa, pb = a @ axis, b @ axis
            if pa.max() < pb.min() or pb.max() < pa.min():
                return False
    return True


def _inside(points, poly):
    """All points strictly inside the convex, counter-clockwise polygon."""
    for i in range(4):
        a, b = poly[i], poly[(i + 1) % 4]
        cross = (b[0] - a[0]) * (points[:, 1] - a[1]) - (b[1] - a[1]) * (points[:, 0] - a[0])
        if np.any(cross <= 0):
            return False
    return True


def test_perimeter_points_spacing_and_corners():
    pts = perimeter_points(0.8, 0.4, 0.08)
    gaps = np.linalg.norm(np.diff(np.vstack([pts, pts[:1]]), axis=0), axis=1)
    assert gaps.max() <= 0.08 + 1e-12
    for corner in ([0.8, 0.4], [-0.8, 0.4], [-0.8, -0.4], [0.8, -0.4]):
        assert np.min(np.linalg.norm(pts - corner, axis=1)) < 1e-12


@settings(max_examples=300, deadline=None)
@given(px=st.floats(-1.5, 1.5), py=st.floats(-1.5, 1.5), pyaw=st.floats(-np.pi, np.pi),
       wyaw=st.floats(-np.pi, np.pi), whx=st.floats(0.02, 0.3), why=st.floats(0.02, 1.0))
def test_overlap_implies_a_point_inside_its_margin(px, py, pyaw, wyaw, whx, why):
    hx, hy = PAYLOAD_HALF[0], PAYLOAD_HALF[1]
    board = _corners(px, py, hx, hy, pyaw)
    wall = _corners(0.0, 0.0, whx, why, wyaw)
    if not _rectangles_overlap(board, wall) or _inside(wall, board):
        return  # a wall wholly inside the board cannot be reached without crossing its edge first
    R = np.array([[np.cos(pyaw), -np.sin(pyaw)], [np.sin(pyaw), np.cos(pyaw)]])
    points = PAYLOAD_POINTS_LOCAL @ R.T + [px, py]
    walls = np.array([[[0.0, 0.0, whx, why, wyaw]]])
    sd = point_box_distance(points[None], walls)[0]
    assert sd.min() - SafetyConfig().payload_margin < 0.0
