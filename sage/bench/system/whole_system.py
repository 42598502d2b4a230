"""``system[method][n]``: end-to-end environment steps/s of the whole system
(router, shield, learner, ``n`` actor processes, all under
``deploy.supervisor``) vs the same services as threads of one process
(in-process mode), for each of ``methods``; beside each, the learner's share
of wall time inside updates (the rest it waits for data), the cores each
component used (``cpu``), and the ratio to ``physics_bound``: raw MuJoCo
stepping the same model with the same controls on one core (``sage bench
env``'s bound), measured right before and right after that method's phase,
with no service running, and averaged (``physics_bound_before`` /
``_after``; ``*_ratio_range``: the ratio to the higher and to the lower of
the two). The bound moves between consecutive measurements on a shared host
(docs/scaling.md), so one taken minutes away from the figure it divides is
not a ratio of the same run. Steady state: counted from the services'
``status`` heartbeats over ``measure_s`` after every actor stepped for
``warmup_s``."""
from __future__ import annotations

import threading
import time
from pathlib import Path

from common import keys
from common.transport import Bus
from deploy.supervised_run import router_spec, service_specs
from deploy.supervisor import free_tcp_port
from sage.bench.machine import host_cpus
from sage.bench.system.cpu import bracketed_ratio, cpu_budget
from sage.bench.system.meter import StepMeter
from services.actor.service import ActorService
from services.launcher import ServiceThreads
from services.learner.service import LearnerService
from services.shield.service import ShieldService


def system_phase(bench, method: str) -> dict:
    """Router, shield, learner and actors of ``method``; actors are added
    between the measurements (1, then 2, ...), processes first, then threads."""
    counts = sorted(set(bench.cfg.actor_counts))
    bound_before = bench.measure_physics_bound()
    port = free_tcp_port()
    connect = [f"tcp/127.0.0.1:{port}"]
    cfg, path = bench.train_config(counts[-1], connect, "sys", method=method, learner_defaults=True)
    run = Path(cfg.run_dir)
    multi, learner_busy, cores, restarts, have = {}, {}, {}, {}, 0
    bench.supervise([router_spec(port), *service_specs(path, roles=("shield", "learner"))], run, restart_budget=5)
    bus = Bus.open(connect=connect, mode="client")
    try:
        meter = StepMeter(cfg.run_id)
        bus.subscribe(keys.status_all(cfg.run_id), meter.on_status)
        for n in counts:
            bench.log(f"bench: whole system ({method}), {n} actor process(es)")
            bench.supervise(service_specs(path, roles=("actor",), actor_ids=range(have, n)), run / f"actors-{n}",
                            restart_budget=5)
            have = n
            multi[n] = meter.measure(n, bench.cfg.warmup_s, bench.cfg.measure_s, bench.cfg.start_timeout_s,
                                     bench.check, cpu=bench.cpu_probe)
            learner_busy[n] = meter.window_rates.get("learner/update_s")
            cores[n] = meter.window_cores
            restarts[n] = bench.restarts()
    finally:
        bus.close()
        bench.stop_all()
    inproc, inproc_busy, inproc_cores, failures = inprocess_system(bench, counts, method)
    bound_after = bench.measure_physics_bound()
    multi_ratio = {n: bracketed_ratio(multi[n], bound_before, bound_after) for n in counts}
    inproc_ratio = {n: bracketed_ratio(inproc[n], bound_before, bound_after) for n in counts}
    bound, cpus = multi_ratio[counts[0]]["bound"], host_cpus()
    return {str(n): {"multiprocess": multi[n], "inprocess": inproc[n],
                     "physics_bound": bound, "physics_bound_before": bound_before,
                     "physics_bound_after": bound_after,
                     "multiprocess_ratio_to_physics_bound": multi_ratio[n]["ratio"],
                     "multiprocess_ratio_range": multi_ratio[n]["range"],
                     "inprocess_ratio_to_physics_bound": inproc_ratio[n]["ratio"],
                     "inprocess_ratio_range": inproc_ratio[n]["range"],
                     # seconds inside updates per second of wall time; 1 - this = waiting for data
                     "learner_update_share": learner_busy[n], "inprocess_learner_update_share": inproc_busy[n],
                     "cpu": cpu_budget(cores[n], multi[n], cpus, bound),
                     "inprocess_cpu": cpu_budget(inproc_cores[n], inproc[n], cpus, bound),
                     "restarts": restarts[n], "inprocess_failures": failures[n]}
            for n in counts}


def inprocess_system(bench, counts: list[int], method: str):
    """Steps/s (and the learner's update share) with the services as
    threads; a failed learner thread is reported (it cannot be
    restarted), a failed actor or shield aborts."""
    cfg, _ = bench.train_config(counts[-1], None, "sys-in", method=method, learner_defaults=True)
    bus = Bus.open(inprocess=True)
    group = ServiceThreads(threading.Event())

    def alive():
        fatal = group.failure(ignore=("learner/0",))
        if fatal:
            raise RuntimeError(f"in-process {fatal[0]} failed: {fatal[1]!r}")

    meter = StepMeter(cfg.run_id)
    bus.subscribe(keys.status_all(cfg.run_id), meter.on_status)
    out, busy, cores, failures, have = {}, {}, {}, {}, 0
    try:
        group.start(ShieldService(cfg, bus, 0, stop=group.stop), stop_all_on_error=False)
        group.start(LearnerService(cfg, bus, 0, stop=group.stop), stop_all_on_error=False)
        for n in counts:
            bench.log(f"bench: whole system in-process ({method}), {n} actor thread(s)")
            for i in range(have, n):
                group.start(ActorService(cfg, bus, i, stop=group.stop), stop_all_on_error=False)
            have = n
            out[n] = meter.measure(n, bench.cfg.warmup_s, bench.cfg.measure_s, bench.cfg.start_timeout_s, alive,
                                   cpu=lambda: {"process": time.process_time()})
            busy[n] = meter.window_rates.get("learner/update_s")
            cores[n] = meter.window_cores
            failures[n] = [f"{who}: {exc!r}"[:300] for who, exc in group.errors]
    finally:
        group.join(15)
        bus.close()
    return out, busy, cores, failures
