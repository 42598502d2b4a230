"""``SystemBench``: runs the benchmarks of ``sage bench system`` in order and
assembles one result. Each phase starts its processes once and measures
several things on them (start-up of a torch/MuJoCo process costs seconds, far
more than a measurement window): the services phase (router + shield + echo
child) serves the shield round trips, the parameter broadcasts, the router
rates and the one-actor variants; then the whole system per method; then the
shield shards."""
from __future__ import annotations

import sys
import threading
import time
from dataclasses import asdict
from pathlib import Path

from common.transport import Bus
from deploy.supervised_run import router_spec, service_specs
from deploy.supervisor import ServiceSpec, free_tcp_port
from sage.bench.machine import host_cpus, machine
from sage.bench.system import actor_ratio, param_broadcast, shield_rtt
from sage.bench.system.config import RATIO_TARGET
from sage.bench.system.harness import Harness
from sage.bench.system.router import router_rates
from sage.bench.system.shards import shards_phase
from sage.bench.system.whole_system import system_phase
from services.shield.service import ShieldService


class SystemBench(Harness):
    # two measurements as methods of the bench (their first argument is the bench)
    _rtt = shield_rtt.round_trips
    _broadcast = param_broadcast.latency

    def services_phase(self) -> dict:
        """Router + shield process + echo child: shield round trips, parameter
        broadcasts, router rates, then one actor process with the shield vs
        with a local QP; then the in-process twins of the first two."""
        batches = self.requests()
        pruned = self.pruned(batches)
        local = shield_rtt.local_qp(self, batches)
        port = free_tcp_port()
        connect = [f"tcp/127.0.0.1:{port}"]
        cfg, path = self.train_config(1, connect, "svc", unpaced=True)
        echo = ServiceSpec("echo", [sys.executable, "-m", "sage.bench.system", "echo", "--config", str(path)])
        self.log(f"bench: shield process, round trips for batches {list(batches)}; parameter broadcasts")
        self.supervise([router_spec(port), *service_specs(path, roles=("shield",)), echo], Path(cfg.run_dir))
        bus = Bus.open(connect=connect, mode="client")
        try:
            self._wait_shield(bus, cfg.run_id, self.check)
            rtt = shield_rtt.round_trips(self, bus, cfg.run_id, batches)
            rtt_pruned = shield_rtt.round_trips(self, bus, cfg.run_id, pruned)
            learner = self.params_publisher(cfg, bus)
            params = param_broadcast.latency(self, bus, learner, cfg.run_id, local=False)
            router = router_rates(self, connect, cfg.run_id, batches)
            self.check()
            actor = actor_ratio.one_actor(self, cfg, path, bus, learner)
        finally:
            bus.close()
            self.stop_all()
        rtt_in, params_in = self.inprocess_twins(batches)
        return {"shield_rtt_ms": shield_rtt.table(batches, pruned, rtt, rtt_in, local, rtt_pruned, cfg.run_id),
                "param_broadcast_ms": param_broadcast.figures(params, params_in, learner, cfg.run_id),
                "router_msgs_per_s": router,
                **actor}

    def inprocess_twins(self, batches: dict[int, dict]):
        """Shield round trips and parameter broadcasts with the same shield as a
        thread on a network-less session."""
        cfg_in, _ = self.train_config(1, None, "svc-in")
        bus = Bus.open(inprocess=True)
        stop = threading.Event()
        th = threading.Thread(target=ShieldService(cfg_in, bus, 0, stop=stop).run, daemon=True)
        th.start()
        try:
            self._wait_shield(bus, cfg_in.run_id, lambda: None)
            rtt_in = shield_rtt.round_trips(self, bus, cfg_in.run_id, batches)
            params_in = param_broadcast.latency(self, bus, self.params_publisher(cfg_in, bus), cfg_in.run_id,
                                                local=True)
        finally:
            stop.set()
            th.join(10)
            bus.close()
        return rtt_in, params_in

    def run(self) -> dict:
        t0 = time.monotonic()
        out = {"bench": "system", "config": asdict(self.cfg),
               "host": {"cpus": host_cpus()}, "machine": machine()}
        try:
            # the bound at the start (each system phase measures its own around it)
            out["physics_bound_env_steps_per_s"] = self.measure_physics_bound()
            out.update(self.services_phase())
            out["ratio_target"] = RATIO_TARGET
            out["meets_target"] = bool(out["ratio_vs_local_qp"] >= RATIO_TARGET)
            out["system"] = {m: system_phase(self, m) for m in self.cfg.methods}
            out["shards"] = shards_phase(self)
        finally:
            self.stop_all()
        out["wall_s"] = time.monotonic() - t0
        return out
