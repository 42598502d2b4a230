"""sage/bench/system/: the measuring parts of `sage bench system`.

The whole benchmark starts a dozen processes (over a minute on 2 cores), so
it is run by hand (`sage bench system --json`); here each of its parts is
checked on its own: the steady-state rate from heartbeats, the quantiles, the
local-QP reference actor, the shield round trip against a real in-process
shield, the parameter broadcast measurement and the command line."""
from __future__ import annotations

import argparse
import threading
import time

import numpy as np
import pytest

from common import keys, wire
from sage.bench.system import (
    actor_step_cost,
    bracketed_ratio,
    cpu_ratio,
    QUICK,
    StepMeter,
    SystemBench,
    SystemBenchConfig,
    config_from_args,
    cpu_budget,
    process_cpu_s,
    quantiles_ms,
    register,
    summary_table,
)


def status_msg(run_id: str, role: str, member: str, env_steps: int, extra: dict | None = None) -> bytes:
    body = {"role": role, "id": member, "state": "running", "pid": 1, "uptime_s": 1.0, "version": 0,
            "env_steps": env_steps, "env_steps_per_s": 0.0, "updates": 0, "success_rate": None,
            "shield_p99_s": None, "message": "", "extra": extra or {}}
    return wire.encode("status", body, run_id=run_id, sender=f"{role}/{member}", seq=0)


def test_quantiles_match_numpy():
    x = np.random.default_rng(0).exponential(0.002, size=501)
    q = quantiles_ms(x)
    assert q["n"] == 501
    assert q["p50"] == pytest.approx(1e3 * np.median(x))
    assert q["p99"] == pytest.approx(1e3 * np.sort(x)[495])  # linear interpolation lands on index 495 exactly


def measure_while_feeding(meter: StepMeter, publish, n_actors: int = 1, **kw) -> float:
    """``meter.measure`` (0.5 s window) while a thread calls ``publish(dt)`` every 10 ms,
    ``dt`` = seconds since the start on the clock status envelopes are stamped with."""
    t0 = time.time()
    stop = threading.Event()

    def feed():
        while not stop.is_set():
            publish(time.time() - t0)
            stop.wait(0.01)

    th = threading.Thread(target=feed, daemon=True)
    th.start()
    try:
        return meter.measure(n_actors, warmup_s=0.05, measure_s=0.5, timeout_s=10, **kw)
    finally:
        stop.set()
        th.join()


def test_step_meter_sums_actor_rates_on_the_sender_clock():
    meter = StepMeter("runA")
    rates = {"0": 400.0, "1": 150.0}

    def publish(dt):
        for member, r in rates.items():
            # steps derived from the same clock the envelope is stamped with
            meter.on_status("k", status_msg("runA", "actor", member, 1 + int(r * dt)))
        meter.on_status("k", status_msg("runA", "learner", "0", 10**9))   # not an actor
        meter.on_status("k", status_msg("runB", "actor", "7", 10**9))     # another run

    rate = measure_while_feeding(meter, publish, n_actors=2)
    assert sorted(meter.snapshot()) == ["0", "1"]
    assert rate == pytest.approx(550.0, rel=0.02)


def test_step_meter_rates_the_learners_update_share_each_shards_qps_and_the_actors_loop():
    meter = StepMeter("runA")

    def publish(dt):
        meter.on_status("k", status_msg("runA", "actor", "0", 1 + int(100 * dt),
                                        {"shield_wait_s_total": 0.1 * dt, "loop_cpu_s_total": 0.85 * dt}))
        meter.on_status("k", status_msg("runA", "learner", "0", 0, {"update_s_total": 0.25 * dt}))
        for k, qps in (("0", 300.0), ("1", 50.0)):
            meter.on_status("k", status_msg("runA", "shield", k, 0, {"rows": qps * dt}))

    measure_while_feeding(meter, publish)
    r = meter.window_rates
    assert r["learner/update_s"] == pytest.approx(0.25, rel=0.05)
    assert r["actor/0/shield_wait_s"] == pytest.approx(0.1, rel=0.05)
    assert r["actor/0/loop_cpu_s"] == pytest.approx(0.85, rel=0.05)
    assert r["shield/0/rows"] == pytest.approx(300.0, rel=0.05) and r["shield/1/rows"] == pytest.approx(50.0, rel=0.05)


def test_step_meter_takes_each_components_cores_over_the_same_window():
    meter = StepMeter("runA")
    t0 = time.monotonic()

    def cpu():   # a component that used 0.75 of a core all along, one that used none, one restarted
        restarted = 1.0 if (time.monotonic() - t0) < 0.3 else 0.1
        return {"actor-0": 0.75 * (time.monotonic() - t0), "router": 2.0, "learner": restarted}

    measure_while_feeding(meter, lambda dt: meter.on_status("k", status_msg("runA", "actor", "0", 1 + int(100 * dt))),
                          cpu=cpu)
    assert meter.window_cores["actor-0"] == pytest.approx(0.75, rel=0.02)
    assert meter.window_cores["router"] == 0.0 and "learner" not in meter.window_cores


def test_bracketed_ratio_divides_by_the_bounds_measured_around_the_figure():
    r = bracketed_ratio(3000.0, 6000.0, 4000.0)
    assert r["bound"] == pytest.approx(5000.0) and r["ratio"] == pytest.approx(0.6)   # 3000 / mean(6000, 4000)
    assert r["range"] == pytest.approx([0.5, 0.75])         # to the higher bound, to the lower
    same = bracketed_ratio(2500.0, 5000.0, 5000.0)
    assert same["ratio"] == pytest.approx(0.5) and same["range"] == pytest.approx([0.5, 0.5])
    with pytest.raises(ValueError):
        bracketed_ratio(1.0, 0.0, 5000.0)


def test_cpu_budget_is_the_cost_of_an_env_step_and_the_rate_the_cores_allow():
    b = cpu_budget({"learner-0": 0.9, "actor-0": 0.8, "shield-0": 0.3}, env_steps_per_s=2000.0,
                   host_cpus=2, physics_bound=5000.0)
    assert b["core_us_per_env_step"] == pytest.approx({"actor-0": 400.0, "learner-0": 450.0, "shield-0": 150.0})
    assert b["core_us_per_env_step_total"] == pytest.approx(1000.0)
    # 1,000 core-us per step on 2 cores: at most 2,000 steps/s, 0.4 of the physics bound
    assert b["cpu_bound_env_steps_per_s"] == pytest.approx(2000.0)
    assert b["cpu_bound_ratio_to_physics_bound"] == pytest.approx(0.4)
    assert cpu_budget({}, 100.0, 2, 1.0) == {} and cpu_budget({"a": 1.0}, 0.0, 2, 1.0) == {}


def test_process_cpu_s_reads_a_live_process_and_none_otherwise():
    import os
    import subprocess
    import sys
    if not os.path.exists(f"/proc/{os.getpid()}/stat"):
        pytest.skip("no /proc on this system")
    before = process_cpu_s(os.getpid())
    deadline = time.process_time() + 0.3
    while time.process_time() < deadline:   # burn 0.3 s of this process's CPU
        pass
    after = process_cpu_s(os.getpid())
    # all threads count on both clocks, so at least the 0.3 s burned (less a 10 ms tick);
    # the upper bound only catches wrong units (other threads may add a little)
    assert 0.28 <= after - before < 1.0
    child = subprocess.Popen([sys.executable, "-c", "pass"])
    child.wait()
    assert process_cpu_s(child.pid) is None      # reaped: gone
    assert process_cpu_s(-1) is None


def test_step_meter_times_out_and_propagates_failures():
    meter = StepMeter("runA")
    meter.on_status("k", status_msg("runA", "actor", "0", 0))  # up, not stepping
    with pytest.raises(TimeoutError):
        meter.measure(1, 0.0, 0.1, timeout_s=0.2)

    def broken():
        raise RuntimeError("service died")

    with pytest.raises(RuntimeError, match="service died"):
        meter.measure(1, 0.0, 0.1, timeout_s=5, alive=broken)


def test_local_qp_actor_executes_the_exact_qp():
    from common.safety_rows import SafetyRows
    from common.shield.qp import qp_violation, solve_cbf_qp
    from common.shield.random_problems import random_cbf_problems
    from sage.bench.system import LocalQPActor
    from services.config import TrainConfig

    actor = LocalQPActor(TrainConfig(run_id="r", method="happo_cbf"), None, 0)
    a, C, c, _ = random_cbf_problems(np.random.default_rng(1), 16)
    rows, fixed = np.ones(c.shape, bool), np.zeros(a.shape, bool)
    a_exec, status = actor.filter_actions(a, SafetyRows(C, c, rows, fixed))
    assert (status == 0).all()
    ref = solve_cbf_qp(a, C, c, rows, fixed)
    np.testing.assert_allclose(a_exec, ref.a_exec, atol=1e-12)
    assert np.all(qp_violation(a_exec, C, c, rows) <= 1e-6)
    assert np.abs(a_exec - a).max() > 1e-3  # the rows were active: something was filtered
    assert actor.rtt.quantile(0.5) is not None


class _ParamsPublisher:
    """Stands in for the learner: the bench only calls ``publish_params``."""

    def __init__(self, bus, run_id):
        self.bus, self.run_id, self.version, self.seq = bus, run_id, 0, 0

    def publish_params(self):
        body = {"version": self.version, "incarnation": "i", "method": "happo_cbf",
                "params": {"carrier_0/W": np.ones((15, 8))}, "settings": {"kappa": 1.0}}
        self.bus.publish(keys.params(self.run_id),
                         wire.encode("params", body, run_id=self.run_id, sender="learner/0", seq=self.seq))
        self.seq += 1


def test_shield_round_trip_and_broadcast_in_process(tmp_path):
    from common.shield.qp import solve_cbf_qp
    from common.transport import Bus
    from services.shield.service import ShieldService

    cfg = SystemBenchConfig(batch_sizes=(1, 8), rtt_requests=5, broadcasts=4)
    bench = SystemBench(cfg, tmp_path, log=lambda _t: None)
    batches = bench.requests()
    assert {B: b["a_prop"].shape for B, b in batches.items()} == {1: (1, 9), 8: (8, 9)}
    assert batches[8]["C"].shape[1:] == (34, 9) and batches[8]["row_mask"].any()
    run_cfg, _ = bench.train_config(1, None, "t")
    bus = Bus.open(inprocess=True)
    stop = threading.Event()
    shield = ShieldService(run_cfg, bus, 0, stop=stop)
    th = threading.Thread(target=shield.run, daemon=True)
    th.start()
    try:
        bench._wait_shield(bus, run_cfg.run_id, lambda: None)
        rtt = bench._rtt(bus, run_cfg.run_id, batches)
        params = bench._broadcast(bus, _ParamsPublisher(bus, run_cfg.run_id), run_cfg.run_id, local=True)
        # the shield answered with the exact QP (what the actor would execute)
        b = batches[8]
        reply = bus.request(keys.shield(run_cfg.run_id), wire.encode("shield_req", b, run_id=run_cfg.run_id,
                                                                     sender="cli/t", seq=99), timeout=10)
        got = wire.decode(reply.ok, run_id=run_cfg.run_id, expect="shield_rep").body["a_exec"]
        np.testing.assert_allclose(got, solve_cbf_qp(b["a_prop"], b["C"], b["c"], b["row_mask"],
                                                     b["fixed_mask"]).a_exec, atol=1e-9)
    finally:
        stop.set()
        th.join(10)
        bus.close()
    assert {B: r["n"] for B, r in rtt.items()} == {1: 5, 8: 5}
    assert all(0 < r["p50"] <= r["p99"] for r in rtt.values())
    assert params["n"] == 4 and 0 < params["p50"] <= params["p99"]
    assert shield.n_requests >= 2 * (10 + 5)  # warm-up + timed requests all reached the shield


def test_command_line_and_table():
    p = argparse.ArgumentParser()
    commands = p.add_subparsers()
    bench = commands.add_parser("bench").add_subparsers()
    register(commands, bench)
    args = p.parse_args(["bench", "system", "--quick", "--json", "--actors", "1,2"])
    cfg = config_from_args(args)
    assert cfg.actor_counts == QUICK["actor_counts"] and cfg.measure_s == QUICK["measure_s"] and args.json
    args = p.parse_args(["bench", "system", "--actors", "1,2", "--batch-sizes", "1,32", "--seconds", "3"])
    cfg = config_from_args(args)
    assert (cfg.actor_counts, cfg.batch_sizes, cfg.measure_s) == ((1, 2), (1, 32), 3.0)
    with pytest.raises(ValueError):
        config_from_args(p.parse_args(["bench", "system", "--actors", "0"]))
    args = p.parse_args(["bench", "system", "--methods", "happo,sage", "--shards", "1,2", "--shard-actors", "2,4"])
    cfg = config_from_args(args)
    assert (cfg.methods, cfg.shard_counts, cfg.shard_actor_counts) == (("happo", "sage"), (1, 2), (2, 4))
    with pytest.raises(ValueError):
        config_from_args(p.parse_args(["bench", "system", "--methods", "nope"]))
    one = {"multiprocess": 120.0, "inprocess": 60.0, "multiprocess_ratio_to_physics_bound": 0.3,
           "inprocess_ratio_to_physics_bound": 0.15, "learner_update_share": 0.4,
           "inprocess_learner_update_share": None, "restarts": {}, "inprocess_failures": [],
           "cpu": cpu_budget({"actor-0": 0.5, "learner-0": 0.7}, 120.0, 2, 400.0), "inprocess_cpu": {}}
    result = {"physics_bound_env_steps_per_s": 400.0, "system": {"sage": {"1": one}},
              "shards": {"2": {"4": {"actor_env_steps_per_s": 900.0, "qps_served": 880.0, "qps_per_shard": {}}}},
              "shield_rtt_ms": {"8": {"p50": 3.9, "p99": 4.3, "inprocess_p50": 3.4, "inprocess_p99": 3.9,
                                      "local_qp_p50": 0.07, "local_qp_p99": 0.1, "pruned_p50": 0.5,
                                      "pruned_p99": 0.9, "bytes": 91000, "pruned_bytes": 9100}},
              "param_broadcast_ms": {"p50": 2.5, "p99": 4.0, "inprocess_p50": 0.9, "inprocess_p99": 1.1,
                                     "bytes": 27547},
              "actor_steps_per_s": {"shield_service": 175.0, "local_qp": 212.0, "shield_service_pipelined": 170.0,
                                    "shield_service_full_rows": 150.0}, "ratio_vs_local_qp": 0.83,
              "ratio_target": 0.7}
    table = summary_table(result)
    assert "physics bound" not in table.split("\n", 1)[1]   # a result without the bracketing bounds
    one.update(physics_bound_before=410.0, physics_bound_after=390.0)
    assert "sage: physics bound 410 before, 390 after its phase" in summary_table(result)
    assert "ratio 0.83" in table and "B=8" in table and "27547 B" in table and "91000 / 9100" in table
    assert "full rows 150.0" in table and "pipelined 170.0" in table
    assert "sage" in table and "(0.30,  0.40)" in table and "2 shard(s), 4 actors" in table
    assert "actor-0 4167, learner-0 5833; total 10000 -> the host's cores allow 200 (0.50 x bound)" in table
    assert "in-process core-us" not in table
    assert "core-us per env step (actor" not in table   # a result without the CPU figures
    result["actor_core_us_per_env_step"] = {"shield_service": {"actor": 400.0, "host": 520.0},
                                            "local_qp": {"actor": 380.0, "host": 390.0}}
    result["cpu_ratio_vs_local_qp"] = 0.75
    assert ("shield service 400 / 520, local QP 380 / 390; CPU ratio 0.75") in summary_table(result)


def test_actor_step_cost_counts_the_processes_a_step_needs():
    cores = {"actor-0": 0.9, "router": 0.05, "shield-0": 0.2, "echo": 0.01}
    # 2,000 env steps/s: the actor 450 core-us per step; with router and shield 575
    assert actor_step_cost(cores, 2000.0, True) == pytest.approx({"actor": 450.0, "host": 575.0})
    # beside a local QP an idle shield is not part of the step
    assert actor_step_cost(cores, 2000.0, False) == pytest.approx({"actor": 450.0, "host": 475.0})
    assert actor_step_cost(cores, 0.0, True) == {} and actor_step_cost({"router": 0.1}, 10.0, True) == {}
    local = [{"actor": 300.0, "host": 310.0}, {"actor": 350.0, "host": 330.0}, {}]
    service = [{"actor": 380.0, "host": 400.0}, {"actor": 390.0, "host": 440.0}, {"actor": 390.0, "host": 420.0}]
    assert cpu_ratio(local, service) == pytest.approx(320.0 / 420.0)   # medians of the rounds that have it
    assert cpu_ratio([{}], service) is None


def test_unpaced_actors_get_a_config_in_bounds_and_a_new_version_without_backlog(tmp_path):
    """The shield/actor phases' actors must never wait for a learner: their config
    stays within ``actor.max_chunks_ahead``'s bound (it resolves), and the bench's
    feeder publishes a new version each time with no backlog (which would report
    every chunk unsettled, nothing consuming them, and pace the actors)."""
    from common.transport import Bus
    from services.config import ActorConfig

    bench = SystemBench(SystemBenchConfig(), tmp_path, log=lambda _t: None)
    cfg, _ = bench.train_config(1, None, "u", unpaced=True)
    assert cfg.actor.max_chunks_ahead == ActorConfig.__dataclass_fields__["max_chunks_ahead"].metadata["range"][2]
    paced, _ = bench.train_config(1, None, "p")
    assert paced.actor.max_chunks_ahead == ActorConfig().max_chunks_ahead
    bus = Bus.open(inprocess=True)
    got = []
    bus.subscribe(keys.params(cfg.run_id),
                  lambda _k, payload: got.append(wire.decode(payload, run_id=cfg.run_id, expect="params").body))
    feeder = bench.feed_params(bench.params_publisher(cfg, bus), period_s=0.01)
    try:
        deadline = time.monotonic() + 20
        while len(got) < 3 and time.monotonic() < deadline:
            time.sleep(0.01)
    finally:
        feeder.stop()
        bus.close()
    versions = [b["version"] for b in got]
    assert len(versions) >= 3 and versions == sorted(set(versions))   # a new version every time
    assert all(b.get("chunks_received") is None and b.get("chunks_waiting") is None for b in got)
