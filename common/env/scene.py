"""The drawn layouts of K envs, laid out as the kernels read them (``SceneBatch``), and the
layout streams (``layout_rng``).

Each env of a ``BatchEnv`` runs its episode in its own layout (``scenarios.draw_layout``),
drawn at the episode's reset. The walls (``walls [K,W,5]``, kernel tables ``tables [K,6,W]``)
are the ones the physics, the observations, the clearance and the safety rows all read; the
dense routes are padded to a common length (``route_points [K,N,2]``, ``route_s``,
``route_heading`` [K,N]; env k's route is the first ``route_n[k]`` samples, ``route_ds[k]``
apart).

Layout streams. The layout of env k's episode e in a ``BatchEnv`` of seed ``seed`` is drawn from
``SeedSequence(seed, spawn_key=(LAYOUT_STREAM, purpose, k, e))``: a pure function of
(purpose, seed, env, episode), apart from every other draw of the env (start pose, mass, noise),
so changing those settings never moves a layout. ``purpose`` is ``"train"`` (the actors' envs)
or ``"eval"`` (every evaluation: common/evaluation/deployment.py, the scripted calibration):
different spawn keys give independent streams, so evaluation runs on held-out layouts even
where a training seed and an evaluation seed are the same integer.
"""
from __future__ import annotations

import inspect
import math

import numpy as np

from common.env.geometry import WallSet, wall_table
from common.env.scenarios import Layout, Route

LAYOUT_STREAM = 0x1A7   # spawn-key tag of the layout streams (no other stream of the env uses it)
PURPOSES = {"train": 0, "eval": 1}
# Route.project's search window (its defaults), for the snapshot kernel's inlined projection
PROJECT_BACK, PROJECT_AHEAD = (inspect.signature(Route.project).parameters[name].default
                               for name in ("back", "ahead"))


def layout_rng(seed, purpose: str, env: int, episode: int) -> np.random.Generator:
    """The generator of env ``env``'s episode ``episode`` layout (module docstring)."""
    if purpose not in PURPOSES:
        raise ValueError(f"layout purpose must be one of {sorted(PURPOSES)}, got {purpose!r}")
    return np.random.default_rng(np.random.SeedSequence(
        seed, spawn_key=(LAYOUT_STREAM, PURPOSES[purpose], int(env), int(episode))))


def project_width(ds: float) -> int:
    """Samples in Route.project's search window (as it computes it)."""
    return math.ceil((PROJECT_BACK + PROJECT_AHEAD) / ds) + 1


class SceneBatch:
    """Per-env walls and routes of K envs (module docstring); ``set(k, layout)`` installs one."""

    def __init__(self, num_envs: int, layout: Layout):
        K, W = num_envs, len(layout.walls)
        self.K, self.W = K, W
        self.walls = np.empty((K, W, 5))
        self.tables = np.empty((K, 6, W))
        self.layouts: list[Layout] = [layout] * K
        self.routes: list[Route] = [Route(layout.route)] * K
        self.wallsets: list[WallSet] = [WallSet(layout.walls)] * K
        self._alloc(len(self.routes[0].s))
        for k in range(K):
            self._write(k)

    def _alloc(self, n: int):
        K = self.K
        self.route_points = np.zeros((K, n, 2))
        self.route_s = np.zeros((K, n))
        self.route_heading = np.zeros((K, n))
        self.route_n = np.zeros(K, np.int64)
        self.route_ds = np.ones(K)
        self.route_width = np.ones(K, np.int64)
        self.route_length = np.zeros(K)

    def _write(self, k: int):
        route, walls = self.routes[k], self.layouts[k].walls
        if len(walls) != self.W:
            raise ValueError(f"a layout of this scenario has {len(walls)} walls, the model {self.W}")
        n = len(route.s)
        if n > self.route_points.shape[1]:   # a longer route than any so far: grow the padding
            self._alloc(n + n // 8)
            for j in range(self.K):
                if j != k:
                    self._write_route(j)
        self._write_route(k)
        self.walls[k] = walls
        self.tables[k] = wall_table(walls)

    def _write_route(self, k: int):
        route = self.routes[k]
        n = len(route.s)
        self.route_points[k, :n] = route.points
        self.route_s[k, :n] = route.s
        self.route_heading[k, :n] = route.heading
        self.route_points[k, n:] = route.points[-1]   # padding never read (indices < route_n)
        self.route_n[k] = n
        self.route_ds[k] = route.ds
        self.route_width[k] = project_width(route.ds)
        self.route_length[k] = route.length

    def set(self, k: int, layout: Layout):
        """Env k runs in ``layout`` from now on."""
        if layout is not self.layouts[k]:
            self.layouts[k] = layout
            self.routes[k] = Route(layout.route)
            self.wallsets[k] = WallSet(layout.walls)
            self._write(k)
