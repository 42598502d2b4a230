"""``sage bench system --json``: figures of the distributed system, each next
to its in-process twin. One benchmark per module, each documenting its keys:

* ``shield_rtt``: ``shield_rtt_ms[B]``, batched shield round trips (process,
  in-process, local QP call, pruned rows).
* ``param_broadcast``: ``param_broadcast_ms``, publish -> decoded in another process.
* ``router``: ``router_msgs_per_s``, messages through the router.
* ``actor_ratio``: ``ratio_vs_local_qp``, ``pipelining_gain``, ``row_pruning_gain``
  and the CPU cost of one actor's env step.
* ``whole_system``: ``system[method][n]``, steps/s of the whole system vs threads.
* ``shards``: ``shards[k][n]``, shield shards serving actors.

Shared parts: ``config`` (``SystemBenchConfig``), ``meter`` (``StepMeter``:
rates from heartbeats), ``cpu`` (where the cores go, ``bracketed_ratio``),
``harness`` (run configs, supervised processes), ``children`` (the bench's
``local-actor`` and ``echo`` processes, ``python -m sage.bench.system``),
``driver`` (``SystemBench``: the order of the phases) and ``cli`` (flags and
the summary table)."""
from sage.bench.machine import host_cpus
from sage.bench.system.children import LocalQPActor, ack_key, echo_main, main
from sage.bench.system.cli import cmd_bench_system, config_from_args, register, summary_table
from sage.bench.system.config import QUICK, RATIO_TARGET, SystemBenchConfig
from sage.bench.system.cpu import (actor_step_cost, bracketed_ratio, cpu_budget, cpu_ratio, median_cost,
                                   process_cpu_s)
from sage.bench.system.driver import SystemBench
from sage.bench.system.meter import Repeater, StepMeter, quantiles_ms

__all__ = ["LocalQPActor", "QUICK", "RATIO_TARGET", "Repeater", "StepMeter", "SystemBench", "SystemBenchConfig",
           "ack_key", "actor_step_cost", "bracketed_ratio", "cmd_bench_system", "config_from_args", "cpu_budget",
           "cpu_ratio", "echo_main", "host_cpus", "main", "median_cost", "process_cpu_s", "quantiles_ms",
           "register", "summary_table"]
