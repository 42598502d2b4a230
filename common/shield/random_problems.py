"""Random CBF-like QP instances for the shield benchmark and tests.

Rows look like one-step CBF rows: unit-ish normals (norm in [0.8, 1.2]) and
offsets placed relative to a known safe action x0 inside the box, so every
instance is feasible. A chosen fraction of rows is violated by the proposal
(these are the rows the shield has to act on); the others hold at both the
proposal and x0 with a random margin.
"""
from __future__ import annotations

import numpy as np


def random_cbf_problems(rng: np.random.Generator, batch: int, rows: int = 34, d: int = 9,
                        violated_frac: float = 1 / 3, box: float = 1.0):
    """Return (a_prop [B,d], C [B,M,d], c [B,M], x0 [B,d]) with x0 feasible for every row."""
    x0 = rng.uniform(-0.8 * box, 0.8 * box, size=(batch, d))
    a = rng.uniform(-box, box, size=(batch, d))
    normals = rng.normal(size=(batch, rows, d))
    normals /= np.linalg.norm(normals, axis=2, keepdims=True)
    normals *= rng.uniform(0.8, 1.2, size=(batch, rows, 1))
    gap = np.einsum("bmd,bd->bm", normals, x0 - a)
    violated = rng.random((batch, rows)) < violated_frac
    # A violated row must separate a from x0: orient its normal toward x0.
    flip = violated & (gap < 0)
    normals[flip] *= -1.0
    gap = np.where(flip, -gap, gap)
    na = np.einsum("bmd,bd->bm", normals, a)
    nx0 = na + gap
    t = rng.uniform(0.2, 1.0, size=(batch, rows))
    c_violated = na + t * gap  # in (n·a, n·x0]: violated at a, satisfied at x0
    c_held = np.minimum(na, nx0) - rng.exponential(0.2, size=(batch, rows))
    c = np.where(violated & (gap > 1e-9), c_violated, c_held)
    return a, normals, c, x0
