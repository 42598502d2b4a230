"""``SafetyRows``: one control step's safety constraints for B joint actions,
the one value the env produces and the proposal step (SAIL), the exact QP,
the shield service, evaluation and recording accept.

    C a >= c   on the rows where row_mask is True          (Eq. qpshield)
    a[fixed_mask] = the measured human action              (exogenous block)

Shapes: C [B, M, d], c [B, M], row_mask [B, M] bool, fixed_mask [B, d] bool,
d = ``common.spec.JOINT_ACT_DIM``. Arrays are held, not copied.
"""
from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np

VIOLATION_TOL = 1e-6   # an action violates a row when c - C a exceeds this (proposal-violation rates)


@dataclass(frozen=True)
class SafetyRows:
    C: np.ndarray
    c: np.ndarray
    row_mask: np.ndarray
    fixed_mask: np.ndarray

    FIELDS = ("C", "c", "row_mask", "fixed_mask")

    @classmethod
    def of(cls, step: Mapping) -> "SafetyRows":
        """The rows of an env ``reset``/``step`` output, a chunk step or a wire body."""
        return cls(step["C"], step["c"], step["row_mask"], step["fixed_mask"])

    def as_dict(self) -> dict[str, np.ndarray]:
        return {k: getattr(self, k) for k in self.FIELDS}

    @property
    def batch(self) -> int:
        return int(np.shape(self.C)[0])

    def select(self, idx) -> "SafetyRows":
        return SafetyRows(*(np.asarray(getattr(self, k))[idx] for k in self.FIELDS))

    @property
    def n_rows(self) -> int:
        """M, the number of row slots per problem."""
        return int(np.shape(self.C)[1])

    def padded(self, M: int) -> "SafetyRows":
        """The same constraints in ``M >= self.n_rows`` row slots: the added slots are
        zero rows (C = 0, c = 0) with row_mask False, which every consumer ignores.
        Returns ``self`` when nothing is to add."""
        C, c, mask = np.asarray(self.C), np.asarray(self.c), np.asarray(self.row_mask)
        B, m = C.shape[:2]
        if M < m:
            raise ValueError(f"cannot pad {m} rows down to {M}")
        if M == m:
            return self
        extra = M - m
        return SafetyRows(np.concatenate([C, np.zeros((B, extra) + C.shape[2:], C.dtype)], axis=1),
                          np.concatenate([c, np.zeros((B, extra), c.dtype)], axis=1),
                          np.concatenate([mask, np.zeros((B, extra), mask.dtype)], axis=1),
                          self.fixed_mask)

    @staticmethod
    def concat(parts: list["SafetyRows"], pad: bool = False) -> "SafetyRows":
        """Stack along the batch. ``pad``: parts may have different M; all are padded
        (``padded``) to the largest first. Without it their M must agree."""
        if pad:
            M = max(p.n_rows for p in parts)
            parts = [p.padded(M) for p in parts]
        return SafetyRows(*(np.concatenate([np.asarray(getattr(p, k)) for p in parts]) for k in SafetyRows.FIELDS))

    def residual(self, a: np.ndarray) -> np.ndarray:
        """c - C a per row [..., M] (positive = violated), -inf on masked-out rows; any
        leading axes (a [..., d] with C [..., M, d])."""
        r = np.asarray(self.c, np.float64) - np.einsum("...md,...d->...m", np.asarray(self.C, np.float64),
                                                       np.asarray(a, np.float64))
        return np.where(np.asarray(self.row_mask, bool), r, -np.inf)

    def scaled_violation(self, a: np.ndarray) -> np.ndarray:
        """Largest row violation per problem [...], each row's relative to max(1, ||C_i||)
        (the QP's own tolerance convention); -inf where no row is live."""
        scale = np.maximum(1.0, np.linalg.norm(np.asarray(self.C, np.float64), axis=-1))
        return (self.residual(a) / scale).max(axis=-1, initial=-np.inf)
