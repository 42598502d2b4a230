"""Vectorized planar geometry against oriented wall boxes ``(cx, cy, hx, hy, yaw)``."""
from __future__ import annotations

import numpy as np


def wrap(a):
    """Angle(s) wrapped to [-pi, pi)."""
    return (np.asarray(a) + np.pi) % (2 * np.pi) - np.pi


def rot(yaw):
    """Rotation matrices [...,2,2] for yaw [...]."""
    c, s = np.cos(yaw), np.sin(yaw)
    return np.stack([np.stack([c, -s], -1), np.stack([s, c], -1)], -2)


def to_frame(vec, yaw):
    """World vectors [...,2] expressed in frames with heading yaw [...]: R(yaw)^T v."""
    c, s = np.cos(yaw), np.sin(yaw)
    x, y = vec[..., 0], vec[..., 1]
    out = np.empty(np.broadcast_shapes(x.shape, np.shape(c)) + (2,), np.result_type(c, x))  # cheaper than np.stack
    out[..., 0] = c * x + s * y
    out[..., 1] = -s * x + c * y
    return out


def from_frame(vec, yaw):
    """Frame vectors [...,2] to world: R(yaw) v."""
    c, s = np.cos(yaw), np.sin(yaw)
    x, y = vec[..., 0], vec[..., 1]
    out = np.empty(np.broadcast_shapes(x.shape, np.shape(c)) + (2,), np.result_type(c, x))
    out[..., 0] = c * x - s * y
    out[..., 1] = s * x + c * y
    return out


def wall_table(walls) -> np.ndarray:
    """The kernels' layout of boxes ``[W,5]``: ``[6,W]`` rows centre x, centre y, half-size x,
    half-size y, cos and sin of the yaw (one contiguous row per quantity, so the kernels'
    loops over walls vectorize)."""
    walls = np.asarray(walls, dtype=np.float64)
    return np.ascontiguousarray(np.concatenate([walls[..., :4], np.cos(walls[..., 4:5]), np.sin(walls[..., 4:5])],
                                               axis=-1).swapaxes(-1, -2))


class WallSet:
    """Precomputed wall boxes for distance and ray queries."""

    def __init__(self, walls: np.ndarray):
        walls = np.asarray(walls, dtype=np.float64).reshape(-1, 5)
        if len(walls) == 0:
            raise ValueError("a scenario needs at least one wall")
        if np.any(walls[:, 2:4] <= 0):
            raise ValueError("wall half-sizes must be positive")
        self.walls = np.ascontiguousarray(walls)
        self.center = walls[:, :2]
        self.half = walls[:, 2:4]
        self.cos = np.cos(walls[:, 4])
        self.sin = np.sin(walls[:, 4])
        self.table = wall_table(walls)

    # The public queries run numba kernels (common/env/kernels.py) on the flattened points;
    # common/env/reference.py has the same computations in numpy (tests compare the two).
    def _flat(self, pts):
        pts = np.asarray(pts, dtype=np.float64)
        return np.ascontiguousarray(pts.reshape(-1, 2)), pts.shape[:-1]

    def signed_distance(self, pts):
        """Signed distance [...,W] of points [...,2] to each box (negative inside)."""
        from common.env.kernels import signed_distances

        flat, lead = self._flat(pts)
        out = np.empty((len(flat), len(self.walls)))
        signed_distances(flat, self.table, out)
        return out.reshape(lead + (len(self.walls),))

    def nearest(self, pts):
        """(distance [...], vector [...,2] from each point to the nearest wall point)."""
        from common.env.kernels import nearest_walls

        flat, lead = self._flat(pts)
        dist, vec = np.empty(len(flat)), np.empty((len(flat), 2))
        nearest_walls(flat, self.table, dist, vec)
        return dist.reshape(lead), vec.reshape(lead + (2,))

    def ray_distance(self, origin, direction, max_dist: float):
        """Distance along unit rays origin/direction [...,2] to the first box (slab test), capped."""
        from common.env.kernels import ray_distances

        origin, direction = np.broadcast_arrays(np.asarray(origin, np.float64), np.asarray(direction, np.float64))
        flat_o, lead = self._flat(origin)
        flat_d, _ = self._flat(direction)
        out = np.empty(len(flat_o))
        ray_distances(flat_o, flat_d, self.table, float(max_dist), out)
        return out.reshape(lead)
