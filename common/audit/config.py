"""Audit-area configuration: one dataclass, one source of defaults."""
from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class AuditConfig:
    # Tree rendering (Sec. IV-C, Fig. tree): how many largest-|weight| terms a
    # predicate or leaf gain shows before folding the rest into "(k more, |w|<=m)".
    top_terms: int = 3
    # Leaf-tuple audit (Table leaf_interpretability): route progress in [0, 1]
    # is cut into this many equal bins, the "class" labels for purity and NMI.
    progress_bins: int = 10
    # Label-shuffle null: number of permutations R of the progress labels.
    shuffles: int = 200
    # Fig. colortrace: the highlighted episode shows this many most frequent tuples.
    top_tuples: int = 12
    # Seed of the permutation null (the audit is otherwise deterministic).
    seed: int = 0
    # Size budget of one .npz a user loads (recording, params): the arrays its npy
    # headers declare, summed, checked before anything is allocated. A recording of
    # 100 episodes x 600 steps at M = 34 rows is ~0.3 GB.
    max_npz_bytes: int = 4 * 1024**3

    def __post_init__(self) -> None:
        if self.top_terms < 1:
            raise ValueError(f"top_terms must be >= 1, got {self.top_terms}")
        if self.progress_bins < 2:
            raise ValueError(f"progress_bins must be >= 2, got {self.progress_bins}")
        if self.shuffles < 2:
            raise ValueError(f"shuffles must be >= 2 (a std is needed), got {self.shuffles}")
        if self.top_tuples < 1:
            raise ValueError(f"top_tuples must be >= 1, got {self.top_tuples}")
