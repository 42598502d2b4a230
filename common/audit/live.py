"""Live leaf occupancy from the actors' decision-trace stream (wire kind
``trace`` on ``sage/<run>/trace/<actor>``, ``actor.trace_every``): how often
each carrier's tree lands in each leaf, and how often and how much the exact
QP corrects the proposals. ``sage watch`` shows it; pure, so it is tested
without a network."""
from __future__ import annotations

from collections import deque

import numpy as np

from common.safety_rows import VIOLATION_TOL


class LiveOccupancy:
    """Aggregates trace bodies. Occupancy and correction figures are over the
    last ``window`` traces (what the policy does now, not since the start);
    counts of traces and env steps seen are totals."""

    MAX_DEPTH = 12   # without a run's depth: deeper paths are refused (2^D leaf columns)

    def __init__(self, window: int = 200, corrected_tol: float = VIOLATION_TOL, depth: int | None = None):
        self.window = window
        self.depth = depth                   # the run's tree depth: every trace's path must have it
        self.corrected_tol = corrected_tol   # ||a_exec - a_prop|| above this = the QP changed the action
        self._recent: deque[tuple[np.ndarray, np.ndarray]] = deque(maxlen=window)   # (leaf [K,N], corr [K])
        self.traces = 0
        self.versions: dict[int, int] = {}   # actor id -> newest version seen
        self.n_leaves = 0

    def add(self, body: dict) -> None:
        """Add one decoded trace body; a ``ValueError`` (nothing added) when it cannot come
        from trees of this depth: another path length, a leaf outside [0, 2^D), a
        correction norm that is negative or not finite."""
        leaf = np.asarray(body["leaf"], dtype=np.int64)
        corr = np.asarray(body["correction_norm"], dtype=np.float64)
        # a depth-D tree has 2^D leaves; the path length D is the nodes' last axis
        depth = int(np.asarray(body["nodes"]).shape[-1])
        if (self.depth is not None and depth != self.depth) or not 1 <= depth <= self.MAX_DEPTH:
            raise ValueError(f"trace: path length {depth}, the run's trees have depth {self.depth}")
        if leaf.size and (leaf.min() < 0 or leaf.max() >= 2 ** depth):
            raise ValueError(f"trace: leaf {int(leaf.max())} outside 0..{2 ** depth - 1}")
        if not (np.isfinite(corr).all() and (corr >= 0).all()):
            raise ValueError("trace: correction norms must be finite and >= 0")
        self._recent.append((leaf, corr))
        self.traces += 1
        self.versions[int(body["actor_id"])] = int(body["version"])
        self.n_leaves = max(self.n_leaves, 2 ** depth)

    def occupancy(self) -> np.ndarray:
        """[N carriers, n_leaves] fraction of recent decisions in each leaf."""
        if not self._recent:
            return np.zeros((0, 0))
        leaves = np.concatenate([lf for lf, _ in self._recent])          # [sum K, N]
        n = max(self.n_leaves, int(leaves.max()) + 1)
        return np.stack([np.bincount(leaves[:, i], minlength=n) / len(leaves) for i in range(leaves.shape[1])])

    def correction(self) -> tuple[float, float]:
        """(fraction of recent env steps the QP corrected, their mean correction norm)."""
        if not self._recent:
            return float("nan"), float("nan")
        corr = np.concatenate([c for _, c in self._recent])
        on = corr > self.corrected_tol
        return float(on.mean()), float(corr[on].mean()) if on.any() else 0.0

    def table(self) -> list[str]:
        """The watch screen: one row per carrier (leaf occupancy %), the correction line."""
        occ = self.occupancy()
        if occ.size == 0:
            return ["no decision traces yet (the run's actors publish them with actor.trace_every > 0)"]
        head = "carrier " + "".join(f"{'leaf ' + str(j):>9}" for j in range(occ.shape[1]))
        rows = [f"{i:>7} " + "".join(f"{100 * x:8.1f}%" for x in occ[i]) for i in range(occ.shape[0])]
        rate, mean = self.correction()
        versions = ",".join(f"{a}:v{v}" for a, v in sorted(self.versions.items()))
        return [head, *rows, f"QP corrected {100 * rate:.1f}% of steps (mean ||a_exec - a_prop|| {mean:.3f}); "
                             f"{self.traces} traces, last {len(self._recent)} shown; actors {versions}"]
