"""The numpy references of common/shield's row kernels: test oracles, not production code.

``drop_box_redundant_rows`` is ``prune.drop_box_redundant_rows`` in numpy: the kept-row mask
(``prune._keep_fallback``, which production runs itself for a per-column box) and the
compaction scatter, the oracle of ``row_kernels.keep_rows_kernel`` and
``compact_rows_kernel`` (tests/test_row_kernels.py). The answer check's numpy twin,
``verify.verify_answer_fallback``, stays in production: ``verify_answer`` runs it for a
status array that is not of an integer type. Nothing in production imports this module.
"""
from __future__ import annotations

import numpy as np

from common.safety_rows import SafetyRows
from common.shield.prune import DEFAULT_HI, DEFAULT_LO, _arrays, _keep_fallback
from common.shield.qp import QPConfig


def drop_box_redundant_rows(a_prop, rows: SafetyRows, lo=DEFAULT_LO, hi=DEFAULT_HI,
                            config: QPConfig | None = None) -> SafetyRows:
    """``prune.drop_box_redundant_rows`` in numpy (keep mask and scatter)."""
    a, C, c, mask, fixed = _arrays(a_prop, rows)
    keep = _keep_fallback(a, C, c, mask, fixed, lo, hi, config)
    B, M, d = C.shape
    n_keep = keep.sum(axis=1)
    Mp = max(1, int(n_keep.max(initial=0)))
    # kept rows first, in their original order: row (b, m) goes to slot rank = its count
    # among problem b's kept rows; one scatter, padding stays zero / False
    b_idx, m_idx = np.nonzero(keep)
    slot = (np.cumsum(keep, axis=1) - 1)[b_idx, m_idx]
    C_out = np.zeros((B, Mp, d))
    c_out = np.zeros((B, Mp))
    row_out = np.zeros((B, Mp), dtype=bool)
    C_out[b_idx, slot] = C[b_idx, m_idx]
    c_out[b_idx, slot] = c[b_idx, m_idx]
    row_out[b_idx, slot] = mask[b_idx, m_idx]   # a kept non-finite row stays masked out
    return SafetyRows(np.ascontiguousarray(C_out), np.ascontiguousarray(c_out),
                      np.ascontiguousarray(row_out), np.array(fixed, dtype=bool))
