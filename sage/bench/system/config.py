"""What ``sage bench system`` measures and for how long (one dataclass: the
defaults of its flags)."""
from __future__ import annotations

from dataclasses import dataclass

from common.algos.registry import METHODS

RATIO_TARGET = 0.85          # actor with the shield service vs with a local QP (issue 14)


@dataclass
class SystemBenchConfig:
    scenario: str = "narrow_gate"
    method: str = "happo_cbf"          # shield/actor phases: shielded, with the cheapest learner update
    methods: tuple[str, ...] = ("happo", "sage")   # whole-system phases: the cheapest and the dearest learner
    envs_per_actor: int = 32           # the training default (services.config.TrainConfig)
    chunk_len: int = 32                # the training default
    actor_counts: tuple[int, ...] = (1, 2)
    shard_counts: tuple[int, ...] = (1, 2)          # shield shards ...
    shard_actor_counts: tuple[int, ...] = (2, 4)    # ... serving this many actor processes
    warmup_s: float = 2.0              # after every actor stepped, before measuring
    measure_s: float = 6.0             # steady-state window per throughput figure
    start_timeout_s: float = 120.0     # services must be stepping by then
    batch_sizes: tuple[int, ...] = (1, 8, 32, 128)
    rtt_requests: int = 100            # timed shield requests per batch size (after 10 warm-up)
    broadcasts: int = 30               # timed parameter broadcasts
    actor_rounds: int = 3              # each actor variant measured this many times in turn (median)
    seed: int = 0

    def validate(self) -> "SystemBenchConfig":
        if min(self.actor_counts + self.shard_counts + self.shard_actor_counts + self.batch_sizes, default=0) < 1:
            raise ValueError("actor counts, shard counts and batch sizes must be >= 1")
        if not self.methods or set(self.methods) - set(METHODS):
            raise ValueError(f"methods must be some of {METHODS}, got {self.methods}")
        if self.measure_s <= 0 or self.warmup_s < 0 or self.rtt_requests < 1 or self.broadcasts < 1 \
                or self.actor_rounds < 1:
            raise ValueError("need measure_s > 0, warmup_s >= 0, rtt_requests >= 1, broadcasts >= 1, "
                             "actor_rounds >= 1")
        return self


QUICK = dict(actor_counts=(1,), methods=("happo",), shard_counts=(1,), shard_actor_counts=(1,), warmup_s=0.5,
             measure_s=2.0, batch_sizes=(1, 8), rtt_requests=20, broadcasts=5, actor_rounds=1)
