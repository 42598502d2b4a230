"""``sage bench system --json``: figures of the distributed system, each next
to its in-process twin.

* ``system[method][n]``: end-to-end environment steps/s of the whole system
  (router, shield, learner, ``n`` actor processes, all under
  ``deploy.supervisor``) vs the same services as threads of one process
  (in-process mode), for each of ``methods``; beside each, the learner's
  share of wall time inside updates (the rest it waits for data) and the
  ratio to ``physics_bound``: raw MuJoCo stepping the same model with the
  same controls on one core (``sage bench env``'s bound), measured right
  before and right after that method's phase, with no service running, and
  averaged (``physics_bound_before`` / ``_after``; ``*_ratio_range``: the
  ratio to the higher and to the lower of the two). On this host the bound
  moved by up to 70% between consecutive measurements, so a bound taken
  minutes away from the figure it divides is not a ratio of the same run.
  Steady state: counted from the services' ``status`` heartbeats
  (cumulative counters with the sender's clock) over ``measure_s`` after
  every actor stepped for ``warmup_s``.
* ``router_msgs_per_s``: messages one client publishes as fast as it can,
  delivered through the router to another client, per second
  (``delivered`` = the fraction that arrived): ``small`` (a heartbeat's
  size) and ``shield_request`` (an actor's request: the batch size nearest
  ``envs_per_actor``).
* ``shards[k][n]``: ``k`` shield shard processes serving ``n`` actor
  processes (no learner): the actors' steps/s and the QPs/s the shards served.
* ``shield_rtt_ms[B]``: round trip of one batched request of ``B`` QPs to the
  shield process (p50/p99), beside the same request to a shield thread on an
  in-process Zenoh session and the bare ``solve_cbf_qp`` call (``local_qp``).
  Requests carry real safety rows of the scenario.
* ``param_broadcast_ms``: learner parameter message (the learner's own
  ``publish_params``) from publish to decoded in another process
  (``echo`` child, same host, same clock), beside the in-process delivery.
* ``ratio_vs_local_qp``: steps/s of one actor process with the shield service
  in the loop divided by the same actor with a local in-process QP call
  (``LocalQPActor``, synchronous: nothing to overlap a local call with) -- no
  learner, parameters from the bench; both with the default settings
  (synchronous, pruned rows: the local QP solves the same pruned rows).
  ``pipelining_gain``: the pipelined actor (``actor.pipeline``) over the
  default synchronous one, ``row_pruning_gain``: pruned rows (``actor.prune_rows``)
  over full rows, all with the shield service. Each variant is measured
  ``actor_rounds`` times in turn (A B C D A B C D ...) and its median is
  reported, so a slow spell of the machine does not land on one variant.
  ``actor_loop_share`` splits each variant's wall time into blocked on shield
  answers and the rollout thread's CPU. ``actor_core_us_per_env_step`` is what
  an env step cost each variant in CPU (the actor process; ``host``: with the
  router and, where asked, the shield process), and ``cpu_ratio_vs_local_qp``
  the local QP's host cost over the shield service's: the ratio the same cores
  would give if nothing waited, which time-sharing on a loaded machine does not
  move (medians of the rounds). ``shield_rtt_ms`` gives full and pruned
  requests' round trips and sizes in bytes.

Child entry points of the bench (also run under the supervisor):
``python -m sage.bench.system local-actor --config RUN.json --actor-id I``
and ``python -m sage.bench.system echo --config RUN.json``. Their extra key
``sage/<run>/bench/ack`` (msgpack map ``seq, t_sent, t_recv, t_decoded``) is
used by the bench only.
"""
from __future__ import annotations

import argparse
import json
import os
import signal
import sys
import tempfile
import threading
import time
from dataclasses import asdict, dataclass, replace
from pathlib import Path

import msgpack
import numpy as np

from common import keys, wire
from common.algos.registry import METHODS
from common.env.batch_env import BatchEnv
from common.env.scenarios import SCENARIOS
from common.safety_rows import SafetyRows
from common.shield.prune import drop_box_redundant_rows
from common.shield.qp import shield_actions
from common.spec import JOINT_ACT_DIM
from common.transport import Bus
from deploy.sage_run import router_spec, service_specs
from deploy.supervisor import ServiceSpec, Supervisor, SupervisorConfig, free_tcp_port
from sage.bench.env import bench_env
from sage.errors import UsageError, int_list, positive_float, positive_int, user_input
from services.actor.service import ActorService
from services.base import run_entry
from services.config import TrainConfig
from services.launcher import ServiceThreads
from services.learner.service import LearnerService, build_method
from services.shield.service import ShieldService

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


def quantiles_ms(samples_s) -> dict:
    x = np.asarray(samples_s, dtype=float) * 1e3
    return {"p50": float(np.quantile(x, 0.5)), "p99": float(np.quantile(x, 0.99)), "n": int(x.size)}


# ----------------------------------------------------------------- throughput from heartbeats
class StepMeter:
    """Cumulative counters from the services' status heartbeats (sender
    clock): every actor's ``env_steps``, the learner's ``update_s_total`` and
    each shield's ``rows``, to compute steady-state rates over a window."""

    def __init__(self, run_id: str):
        self.run_id = run_id
        self.last: dict[str, tuple[float, float]] = {}        # actor id -> (t, env_steps)
        self.counters: dict[str, tuple[float, float]] = {}    # "learner/update_s" | "shield/<k>/rows" -> (t, value)
        self._lock = threading.Lock()

    def on_status(self, _key: str, payload: bytes) -> None:
        try:
            msg = wire.decode(payload, run_id=self.run_id, expect="status")
        except wire.WireError:
            return
        b, extra = msg.body, msg.body.get("extra") or {}
        with self._lock:
            if b["role"] == "actor":
                self.last[b["id"]] = (msg.t, int(b["env_steps"]))
                for name in ("shield_wait_s", "loop_cpu_s"):
                    if f"{name}_total" in extra:
                        self.counters[f"actor/{b['id']}/{name}"] = (msg.t, float(extra[f"{name}_total"]))
            elif b["role"] == "learner" and "update_s_total" in extra:
                self.counters["learner/update_s"] = (msg.t, float(extra["update_s_total"]))
            elif b["role"] == "shield" and "rows" in extra:
                self.counters[f"shield/{b['id']}/rows"] = (msg.t, float(extra["rows"]))
                if "busy_s_total" in extra:
                    self.counters[f"shield/{b['id']}/busy_s"] = (msg.t, float(extra["busy_s_total"]))

    def snapshot(self) -> dict[str, tuple[float, int]]:
        with self._lock:
            return dict(self.last)

    def counter_snapshot(self) -> dict[str, tuple[float, float]]:
        with self._lock:
            return dict(self.counters)

    def reset(self) -> None:
        with self._lock:
            self.last.clear()
            self.counters.clear()

    def stepping(self, n_actors: int) -> bool:
        snap = self.snapshot()
        return len(snap) >= n_actors and all(s > 0 for _, s in snap.values())

    @staticmethod
    def rates(s0: dict, s1: dict) -> dict[str, float]:
        """Per key: (value change) / (sender-clock time change) between two snapshots."""
        return {k: (v1 - s0[k][1]) / (t1 - s0[k][0]) for k, (t1, v1) in s1.items() if k in s0 and t1 > s0[k][0]}

    def measure(self, n_actors: int, warmup_s: float, measure_s: float, timeout_s: float,
                alive=lambda: None, cpu=None) -> float:
        """Wait until ``n_actors`` actors stepped, let them run ``warmup_s``,
        then sum over actors of steps/s between two snapshots ``measure_s``
        apart (each actor's own clock); the other counters' rates of the same
        window are left in ``window_rates``. ``alive()`` raises if the system broke.
        ``cpu()`` (optional) returns CPU seconds so far by component; the cores each
        used over the same window are left in ``window_cores`` (a component whose
        count went back, i.e. one restarted in the window, is left out)."""
        deadline = time.monotonic() + timeout_s
        while not self.stepping(n_actors):
            alive()
            if time.monotonic() > deadline:
                raise TimeoutError(f"{n_actors} actor(s) not stepping after {timeout_s} s: {self.snapshot()}")
            time.sleep(0.05)
        time.sleep(warmup_s)
        s0, c0 = self.snapshot(), self.counter_snapshot()
        p0, t0 = (cpu() if cpu else {}), time.monotonic()
        time.sleep(measure_s)
        alive()
        s1, c1 = self.snapshot(), self.counter_snapshot()
        p1, t1 = (cpu() if cpu else {}), time.monotonic()
        self.window_rates = self.rates(c0, c1)
        self.window_cores = {k: (v - p0[k]) / (t1 - t0) for k, v in p1.items() if k in p0 and v >= p0[k]}
        return sum(self.rates(s0, s1).values())


# ----------------------------------------------------------------- where the cores go
def host_cpus() -> int:
    """The CPUs this process may run on."""
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)


def process_cpu_s(pid: int) -> float | None:
    """User + system CPU seconds of a live process, all its threads (Linux
    ``/proc/<pid>/stat``, clock-tick resolution); None where unreadable."""
    try:
        with open(f"/proc/{pid}/stat", "rb") as f:
            fields = f.read().rsplit(b")", 1)[1].split()   # the name may hold spaces and ')'
        return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")
    except (OSError, IndexError, ValueError):
        return None


def cpu_budget(cores: dict[str, float], env_steps_per_s: float, host_cpus: int, physics_bound: float) -> dict:
    """What an env step costs the host, from the cores each component used
    while the system made ``env_steps_per_s``: core-microseconds per env step
    by component and in all, and the rate the host's cores would allow at
    that cost if nothing ever waited (``cpu_bound_env_steps_per_s``: host CPUs
    / total cost), also as a fraction of the physics bound. A configuration
    whose CPU bound is below a target cannot reach it by scheduling alone."""
    if not env_steps_per_s > 0 or not cores:
        return {}
    per_step = {k: v / env_steps_per_s * 1e6 for k, v in sorted(cores.items())}
    total = sum(per_step.values())
    bound = host_cpus * 1e6 / total if total > 0 else float("inf")
    return {"cores_used": dict(sorted(cores.items())), "core_us_per_env_step": per_step,
            "core_us_per_env_step_total": total, "cpu_bound_env_steps_per_s": bound,
            "cpu_bound_ratio_to_physics_bound": bound / physics_bound}


def bracketed_ratio(rate: float, before: float, after: float) -> dict:
    """``rate`` against the physics bound measured just before and just after
    it: their mean (``bound``), the ratio to it, and the range from the higher to the lower."""
    if not (before > 0 and after > 0):
        raise ValueError(f"physics bounds must be > 0 (got {before}, {after})")
    bound = (before + after) / 2
    return {"bound": bound, "ratio": rate / bound, "range": [rate / max(before, after), rate / min(before, after)]}


def actor_step_cost(cores: dict[str, float], env_steps_per_s: float, shielded_by_service: bool) -> dict[str, float]:
    """Core-microseconds per env step of one actor-phase window: the actor process's
    own (``actor``) and every process the step needs (``host``): the actor's and the
    router's (chunks and heartbeats), plus the shield's where the actor asks it (an
    idle shield beside a local-QP actor is not counted); the bench's parameter echo
    is left out. Empty when the window has no steps or no CPU reading of the actor."""
    if not env_steps_per_s > 0 or "actor-0" not in cores:
        return {}
    host = sum(v for k, v in cores.items()
               if k in ("actor-0", "router") or (shielded_by_service and k.startswith("shield")))
    return {"actor": cores["actor-0"] / env_steps_per_s * 1e6, "host": host / env_steps_per_s * 1e6}


def median_cost(rounds: list[dict]) -> dict[str, float]:
    """Per figure (``actor``, ``host``), the median over the rounds that have it."""
    names = sorted({k for r in rounds for k in r})
    return {k: float(np.median([r[k] for r in rounds if k in r])) for k in names}


def cpu_ratio(local: list[dict], service: list[dict]) -> float | None:
    """Host cost of an env step with the local QP over that with the shield service
    (medians): the steps/s ratio the same cores would give if nothing waited."""
    a, b = median_cost(local).get("host"), median_cost(service).get("host")
    return a / b if a and b else None


# ----------------------------------------------------------------- the actor with a local QP
class LocalQPActor(ActorService):
    """The actor service with the exact joint CBF-QP (Eq. qpshield) solved
    in-process instead of by the shield service: the reference of
    ``ratio_vs_local_qp``. Synchronous (nothing to overlap a local call with)."""

    def __init__(self, cfg, *args, **kw):
        super().__init__(replace(cfg, actor=replace(cfg.actor, pipeline=False)), *args, **kw)

    def filter_actions(self, a_prop, rows: SafetyRows, asked=None):
        t0 = time.perf_counter()
        # the same QP the shield service is asked, so the ratio is the service's cost
        res = shield_actions(a_prop, self.query_rows(a_prop, rows), backend=self.cfg.shield.backend)
        self.rtt.add(time.perf_counter() - t0)
        return np.asarray(res.a_exec, dtype=np.float64), res.status


def ack_key(run_id: str) -> str:
    return f"{keys.run_root(run_id)}/bench/ack"


def echo_main(argv) -> int:
    """Child: decode every parameter broadcast as an actor would, then ack it
    with the publish time, the receive time and the decoded time."""
    p = argparse.ArgumentParser(prog="python -m sage.bench.system echo")
    p.add_argument("--config", required=True)
    cfg = TrainConfig.load(p.parse_args(argv).config)
    stop = threading.Event()
    for sig in (signal.SIGTERM, signal.SIGINT):
        signal.signal(sig, lambda *_: stop.set())
    bus = Bus.open(connect=cfg.transport.connect, mode=cfg.transport.mode)

    def on_params(_key, payload):
        t_recv = time.time()
        try:
            msg = wire.decode(payload, run_id=cfg.run_id, expect="params")
        except wire.WireError as exc:
            print(f"echo: rejected params ({exc.reason})", file=sys.stderr)
            return
        bus.publish(ack_key(cfg.run_id), msgpack.packb(
            {"seq": msg.seq, "t_sent": msg.t, "t_recv": t_recv, "t_decoded": time.time()}))

    try:
        bus.subscribe(keys.params(cfg.run_id), on_params)
        while not stop.wait(0.2):
            pass
    finally:
        bus.close()
    return 0


# ----------------------------------------------------------------- the harness
class SystemBench:
    """Runs the measurements; each phase starts its processes once and
    measures several things on them (start-up of a torch/MuJoCo process costs
    seconds, far more than a measurement window)."""

    def __init__(self, cfg: SystemBenchConfig, work_dir: Path, log=None):
        self.cfg = cfg.validate()
        self.work = Path(work_dir)
        self.log = log or (lambda text: print(text, file=sys.stderr, flush=True))
        self._n = 0
        self._sups: list = []

    # ------------------------------------------------------------- helpers
    def train_config(self, actors: int, connect: list[str] | None, tag: str, unpaced: bool = False,
                     method: str | None = None, shields: int = 1, learner_defaults: bool = False):
        """A run config for one phase; one chunk per update, so the learner's
        batch does not depend on how many actors are up yet. ``unpaced``: the
        actor never waits for the learner (phase 1 has none: it measures the
        actor's own stepping rate)."""
        self._n += 1
        run_id = f"bench-{tag}-{os.getpid()}-{self._n}"
        cfg = TrainConfig(run_id=run_id, run_dir=str(self.work / run_id), scenario=self.cfg.scenario,
                          method=method or self.cfg.method, actors=actors, shields=shields,
                          envs_per_actor=self.cfg.envs_per_actor,
                          chunk_len=self.cfg.chunk_len, chunks_per_update=1, updates=1_000_000,
                          status_period_s=0.2, eval_episodes=0, checkpoint_every=1_000_000, seed=self.cfg.seed,
                          deploy_probe_every=0,   # a probe would pause the learner mid-measurement
                          mode="supervised",
                          # the whole-system phases train with the method's defaults (what a run costs);
                          # the shield/actor phases have no learner
                          algo={} if learner_defaults else {"epochs": 1, "minibatches": 1})
        if connect:
            cfg.transport.connect, cfg.transport.mode = list(connect), "client"
        cfg.actor.exit_on_unhealthy = True
        if unpaced:
            cfg.actor.max_chunks_ahead = 1 << 30
        cfg.resolve()
        return cfg, cfg.save(Path(cfg.run_dir) / "config.json")

    def supervise(self, specs, run_dir, restart_budget: int = 0):
        """Start ``specs`` under a supervisor. By default a crash fails the
        benchmark; with a ``restart_budget`` crashed services are restarted
        and counted (``restarts`` in the result) instead."""
        cfg = SupervisorConfig(restart_budget=restart_budget, backoff_initial_s=0.2, term_deadline_s=10.0)
        sup = Supervisor(specs, run_dir, cfg, out=sys.stderr)
        self._sups.append(sup)
        sup.start()
        return sup

    def check(self) -> None:
        for sup in self._sups:
            if sup.poll() is not None or any(c.state in ("failed", "done") for c in sup.children):
                bad = {c.spec.name: (c.state, c.last_code) for c in sup.children if c.state != "running"}
                raise RuntimeError(f"a service exited during the benchmark: {bad}; logs in {sup.log_dir}")

    def cpu_probe(self) -> dict[str, float]:
        """CPU seconds so far of every running supervised service, by service name."""
        out = {}
        for sup in self._sups:
            for c in sup.children:
                if c.proc is not None and c.proc.poll() is None:
                    used = process_cpu_s(c.proc.pid)
                    if used is not None:
                        out[c.spec.name] = used
        return out

    def restarts(self) -> dict[str, int]:
        return {c.spec.name: c.starts - 1 for sup in self._sups for c in sup.children if c.starts > 1}

    def stop(self, sup) -> None:
        sup.shutdown("bench done")
        self._sups.remove(sup)

    def stop_all(self) -> None:
        for sup in reversed(list(self._sups)):
            self.stop(sup)

    def requests(self) -> dict[int, dict]:
        """Shield problems per batch size: the scenario's real safety rows at
        reset of ``max(batch_sizes)`` envs, random proposals in the action box."""
        n = max(self.cfg.batch_sizes)
        out = BatchEnv(TrainConfig(scenario=self.cfg.scenario).env_config(), n, seed=self.cfg.seed).reset()
        full = {"a_prop": np.random.default_rng(self.cfg.seed).uniform(-1, 1, size=(n, JOINT_ACT_DIM)),
                **SafetyRows.of(out).as_dict()}
        return {B: {k: np.ascontiguousarray(v[:B]) for k, v in full.items()} for B in self.cfg.batch_sizes}

    @staticmethod
    def pruned(batches: dict[int, dict]) -> dict[int, dict]:
        """The same requests as an actor sends them (``actor.prune_rows``)."""
        return {B: {"a_prop": b["a_prop"], **drop_box_redundant_rows(b["a_prop"], SafetyRows.of(b)).as_dict()}
                for B, b in batches.items()}

    def _learner(self, cfg, bus):
        """The real learner service object, used only for ``publish_params``."""
        learner = LearnerService(cfg, bus, 0)
        learner.method = build_method(cfg)
        return learner

    # ------------------------------------------------------------- measurements
    def _rtt(self, bus, run_id: str, batches: dict[int, dict]) -> dict:
        out = {}
        for B, body in batches.items():
            samples = []
            for i in range(10 + self.cfg.rtt_requests):  # 10 warm-up requests
                payload = wire.encode("shield_req", body, run_id=run_id, sender="cli/bench", seq=i)
                t0 = time.perf_counter()
                reply = bus.request(keys.shield(run_id), payload, timeout=10.0)
                dt = time.perf_counter() - t0
                if reply is None or reply.ok is None:
                    raise RuntimeError(f"shield gave no answer for a batch of {B}: {reply}")
                rep = wire.decode(reply.ok, run_id=run_id, expect="shield_rep")
                if rep.body["a_exec"].shape != (B, JOINT_ACT_DIM):
                    raise RuntimeError(f"shield answered shape {rep.body['a_exec'].shape} for {B} problems")
                if i >= 10:
                    samples.append(dt)
            out[B] = quantiles_ms(samples)
        return out

    def _local_qp(self, batches: dict[int, dict]) -> dict:
        out = {}
        for B, b in batches.items():
            samples = []
            for i in range(10 + self.cfg.rtt_requests):
                t0 = time.perf_counter()
                shield_actions(b["a_prop"], SafetyRows.of(b))
                if i >= 10:
                    samples.append(time.perf_counter() - t0)
            out[B] = quantiles_ms(samples)
        return out

    def _broadcast(self, bus, learner, run_id: str, local: bool) -> dict:
        """``broadcasts`` parameter messages, one at a time; latency publish ->
        decoded, from the echo child's acks or (``local``) a subscriber here."""
        acks: list[dict] = []
        if local:
            def on_params(_k, payload):
                t_recv = time.time()
                msg = wire.decode(payload, run_id=run_id, expect="params")
                acks.append({"seq": msg.seq, "t_sent": msg.t, "t_recv": t_recv, "t_decoded": time.time()})
            bus.subscribe(keys.params(run_id), on_params)
        else:
            bus.subscribe(ack_key(run_id), lambda _k, payload: acks.append(msgpack.unpackb(payload)))
        time.sleep(0.5)  # let the subscriptions propagate through the router
        for i in range(self.cfg.broadcasts + 3):  # the first 3 are warm-up
            n = len(acks)
            learner.version = i
            learner.publish_params()
            deadline = time.monotonic() + 5.0
            while len(acks) == n and time.monotonic() < deadline:
                time.sleep(0.0005)
            time.sleep(0.02)
        lat = [a["t_decoded"] - a["t_sent"] for a in acks[3:]]
        if not lat:
            raise RuntimeError("no parameter broadcast was acknowledged")
        return quantiles_ms(lat)

    @staticmethod
    def _params_bytes(learner, run_id: str) -> int:
        params = {k: np.asarray(v) for k, v in learner.method.policy_params().items()
                  if np.asarray(v).dtype.kind in "fiub"}
        return len(wire.encode("params", {"version": 0, "incarnation": learner.incarnation, "method": "x",
                                          "params": params, "settings": {"kappa": 1.0, "tau": 1.0}},
                               run_id=run_id, sender="learner/0", seq=0))

    def _router_rate(self, connect: list[str], run_id: str, n: int = 20_000, size: int = 300) -> dict:
        """Messages/s from one client through the router to another."""
        key = f"{keys.run_root(run_id)}/bench/flood"
        got, last, done = [0], [0.0], threading.Event()

        def on_msg(_k, _payload):
            got[0] += 1
            last[0] = time.perf_counter()
            if got[0] == n:
                done.set()

        pub, sub = Bus.open(connect=connect, mode="client"), Bus.open(connect=connect, mode="client")
        try:
            sub.subscribe(key, on_msg)
            time.sleep(0.5)   # the subscription reaches the router
            payload = bytes(size)
            t0 = time.perf_counter()
            for _ in range(n):
                pub.publish(key, payload)
            done.wait(10.0)   # a dropped message never arrives: the rate runs to the last delivery
            dt = max(last[0] - t0, 1e-9)
        finally:
            pub.close()
            sub.close()
        return {"msgs_per_s": got[0] / dt, "delivered": got[0] / n, "bytes": size, "sent": n}

    def _wait_shield(self, bus, run_id: str, alive) -> None:
        """Until the shield answers a trivial request (its queryable is declared)."""
        body = {"a_prop": np.zeros((1, JOINT_ACT_DIM)), "C": np.zeros((1, 1, JOINT_ACT_DIM)), "c": np.zeros((1, 1)),
                "row_mask": np.zeros((1, 1), bool), "fixed_mask": np.zeros((1, JOINT_ACT_DIM), bool)}
        payload = wire.encode("shield_req", body, run_id=run_id, sender="cli/bench", seq=0)
        deadline = time.monotonic() + self.cfg.start_timeout_s
        while True:
            reply = bus.request(keys.shield(run_id), payload, timeout=1.0)
            if reply is not None and reply.ok is not None:
                return
            alive()
            if time.monotonic() > deadline:
                raise TimeoutError(f"the shield never answered within {self.cfg.start_timeout_s} s")
            time.sleep(0.05)

    # ------------------------------------------------------------- phase 1: shield, params, one actor
    def services_phase(self) -> dict:
        """Router + shield process + echo child: shield round trips, parameter
        broadcasts, then one actor process with the shield vs with a local QP."""
        batches = self.requests()
        pruned = self.pruned(batches)
        local = self._local_qp(batches)
        port = free_tcp_port()
        connect = [f"tcp/127.0.0.1:{port}"]
        cfg, path = self.train_config(1, connect, "svc", unpaced=True)
        run = Path(cfg.run_dir)
        echo = ServiceSpec("echo", [sys.executable, "-m", "sage.bench.system", "echo", "--config", str(path)])
        self.log(f"bench: shield process, round trips for batches {list(batches)}; parameter broadcasts")
        self.supervise([router_spec(port), *service_specs(path, roles=("shield",)), echo], run)
        bus = Bus.open(connect=connect, mode="client")
        try:
            self._wait_shield(bus, cfg.run_id, self.check)
            rtt = self._rtt(bus, cfg.run_id, batches)
            rtt_pruned = self._rtt(bus, cfg.run_id, pruned)
            learner = self._learner(cfg, bus)
            params = self._broadcast(bus, learner, cfg.run_id, local=False)
            # small (heartbeat-sized) and shield-request-sized messages
            near_k = min(batches, key=lambda B: abs(B - self.cfg.envs_per_actor))   # an actor's request size
            req_bytes = len(wire.encode("shield_req", batches[near_k], run_id=cfg.run_id, sender="a", seq=0))
            router = {"small": self._router_rate(connect, cfg.run_id),
                      "shield_request": self._router_rate(connect, cfg.run_id, n=2_000, size=req_bytes)}
            self.check()
            meter = StepMeter(cfg.run_id)
            bus.subscribe(keys.status_all(cfg.run_id), meter.on_status)
            feeder = _Repeater(learner.publish_params, 0.5)  # actors wait for parameters
            piped_path = replace(cfg, actor=replace(cfg.actor, pipeline=True)).save(run / "config-pipelined.json")
            full_path = replace(cfg, actor=replace(cfg.actor, prune_rows=False)).save(run / "config-full-rows.json")
            actor = {"local_qp": [sys.executable, "-m", "sage.bench.system", "local-actor",
                                  "--config", str(path), "--actor-id", "0"],
                     "shield_service": service_specs(path, roles=("actor",), actor_ids=[0])[0].argv,
                     "shield_service_pipelined": service_specs(piped_path, roles=("actor",), actor_ids=[0])[0].argv,
                     "shield_service_full_rows": service_specs(full_path, roles=("actor",), actor_ids=[0])[0].argv}
            runs: dict[str, list] = {kind: [] for kind in actor}
            costs: dict[str, list] = {kind: [] for kind in actor}
            try:
                for r in range(self.cfg.actor_rounds):
                    for kind, argv in actor.items():
                        self.log(f"bench: one actor process ({self.cfg.envs_per_actor} envs), "
                                 f"{kind.replace('_', ' ')}, round {r + 1}/{self.cfg.actor_rounds}")
                        sub = self.supervise([ServiceSpec("actor-0", argv)], run / f"{kind}-{r}")
                        meter.reset()
                        rate = meter.measure(1, self.cfg.warmup_s, self.cfg.measure_s,
                                             self.cfg.start_timeout_s, self.check, cpu=self.cpu_probe)
                        runs[kind].append((rate, {name: meter.window_rates.get(f"actor/0/{name}")
                                                  for name in ("shield_wait_s", "loop_cpu_s")}))
                        costs[kind].append(actor_step_cost(meter.window_cores, rate, kind != "local_qp"))
                        self.stop(sub)
            finally:
                feeder.stop()
            rates = {kind: float(np.median([rate for rate, _ in v])) for kind, v in runs.items()}
            # the loop shares of the round whose rate is the median (the lower middle one if even)
            loop = {kind: sorted(v, key=lambda x: x[0])[(len(v) - 1) // 2][1] for kind, v in runs.items()}
        finally:
            bus.close()
            self.stop_all()
        # in-process twins: the same shield as a thread on a network-less session
        cfg_in, _ = self.train_config(1, None, "svc-in")
        bus = Bus.open(inprocess=True)
        stop = threading.Event()

        th = threading.Thread(target=ShieldService(cfg_in, bus, 0, stop=stop).run, daemon=True)
        th.start()
        try:
            self._wait_shield(bus, cfg_in.run_id, lambda: None)
            rtt_in = self._rtt(bus, cfg_in.run_id, batches)
            params_in = self._broadcast(bus, self._learner(cfg_in, bus), cfg_in.run_id, local=True)
        finally:
            stop.set()
            th.join(10)
            bus.close()
        table = {str(B): {"p50": rtt[B]["p50"], "p99": rtt[B]["p99"],
                          "inprocess_p50": rtt_in[B]["p50"], "inprocess_p99": rtt_in[B]["p99"],
                          "local_qp_p50": local[B]["p50"], "local_qp_p99": local[B]["p99"],
                          "pruned_p50": rtt_pruned[B]["p50"], "pruned_p99": rtt_pruned[B]["p99"],
                          "bytes": len(wire.encode("shield_req", batches[B], run_id=cfg.run_id, sender="a", seq=0)),
                          "pruned_bytes": len(wire.encode("shield_req", pruned[B], run_id=cfg.run_id, sender="a",
                                                          seq=0)),
                          "requests": rtt[B]["n"]} for B in batches}
        return {"shield_rtt_ms": table,
                "param_broadcast_ms": {"p50": params["p50"], "p99": params["p99"],
                                       "inprocess_p50": params_in["p50"], "inprocess_p99": params_in["p99"],
                                       "bytes": self._params_bytes(learner, cfg.run_id), "broadcasts": params["n"]},
                "router_msgs_per_s": router,
                "actor_steps_per_s": rates,
                "actor_steps_per_s_rounds": {kind: [rate for rate, _ in v] for kind, v in runs.items()},
                # per second of the actor's wall time: blocked on shield answers, and
                # its rollout thread's CPU time (1 - both: descheduled; the bench's actors never pace)
                "actor_loop_share": {kind: {"shield_wait": v["shield_wait_s"], "cpu": v["loop_cpu_s"]}
                                     for kind, v in loop.items()},
                "ratio_vs_local_qp": rates["shield_service"] / rates["local_qp"],
                # the same comparison in CPU: what an env step costs the host's cores (actor,
                # shield and router processes) with the shield service vs with the local QP;
                # medians of the rounds (time-sharing on a loaded machine does not enter it)
                "actor_core_us_per_env_step": {kind: median_cost(v) for kind, v in costs.items()},
                "cpu_ratio_vs_local_qp": cpu_ratio(costs["local_qp"], costs["shield_service"]),
                "pipelining_gain": rates["shield_service_pipelined"] / rates["shield_service"],
                "row_pruning_gain": rates["shield_service"] / rates["shield_service_full_rows"]}

    # ------------------------------------------------------------- phase 2: the whole system
    def system_phase(self, method: str) -> dict:
        """Router, shield, learner and actors of ``method``; actors are added
        between the measurements (1, then 2, ...), processes first, then threads."""
        counts = sorted(set(self.cfg.actor_counts))
        bound_before = self.measure_physics_bound()
        port = free_tcp_port()
        connect = [f"tcp/127.0.0.1:{port}"]
        cfg, path = self.train_config(counts[-1], connect, "sys", method=method, learner_defaults=True)
        run = Path(cfg.run_dir)
        multi, learner_busy, cores, restarts, have = {}, {}, {}, {}, 0
        self.supervise([router_spec(port), *service_specs(path, roles=("shield", "learner"))], run, restart_budget=5)
        bus = Bus.open(connect=connect, mode="client")
        try:
            meter = StepMeter(cfg.run_id)
            bus.subscribe(keys.status_all(cfg.run_id), meter.on_status)
            for n in counts:
                self.log(f"bench: whole system ({method}), {n} actor process(es)")
                self.supervise(service_specs(path, roles=("actor",), actor_ids=range(have, n)), run / f"actors-{n}",
                               restart_budget=5)
                have = n
                multi[n] = meter.measure(n, self.cfg.warmup_s, self.cfg.measure_s, self.cfg.start_timeout_s,
                                         self.check, cpu=self.cpu_probe)
                learner_busy[n] = meter.window_rates.get("learner/update_s")
                cores[n] = meter.window_cores
                restarts[n] = self.restarts()
        finally:
            bus.close()
            self.stop_all()
        inproc, inproc_busy, inproc_cores, failures = self._inprocess_system(counts, method)
        bound_after = self.measure_physics_bound()
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

    def _inprocess_system(self, counts: list[int], method: str):
        """Steps/s (and the learner's update share) with the services as
        threads; a failed learner thread is reported (it cannot be
        restarted), a failed actor or shield aborts."""
        cfg, _ = self.train_config(counts[-1], None, "sys-in", method=method, learner_defaults=True)
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
                self.log(f"bench: whole system in-process ({method}), {n} actor thread(s)")
                for i in range(have, n):
                    group.start(ActorService(cfg, bus, i, stop=group.stop), stop_all_on_error=False)
                have = n
                out[n] = meter.measure(n, self.cfg.warmup_s, self.cfg.measure_s, self.cfg.start_timeout_s, alive,
                                       cpu=lambda: {"process": time.process_time()})
                busy[n] = meter.window_rates.get("learner/update_s")
                cores[n] = meter.window_cores
                failures[n] = [f"{who}: {exc!r}"[:300] for who, exc in group.errors]
        finally:
            group.join(15)
            bus.close()
        return out, busy, cores, failures

    # ------------------------------------------------------------- phase 3: shield shards
    def shards_phase(self) -> dict:
        """``k`` shield shard processes and ``n`` unpaced actor processes (no
        learner; the bench feeds parameters): actor steps/s and QPs/s served."""
        out: dict[str, dict] = {}
        for k in sorted(set(self.cfg.shard_counts)):
            for n in sorted(set(self.cfg.shard_actor_counts)):
                if k > n:
                    continue
                port = free_tcp_port()
                connect = [f"tcp/127.0.0.1:{port}"]
                cfg, path = self.train_config(n, connect, f"shard{k}", unpaced=True, shields=k)
                self.log(f"bench: {k} shield shard(s), {n} actor process(es)")
                self.supervise([router_spec(port), *service_specs(path, roles=("shield", "actor"),
                                                                  actor_ids=range(n), shields=k)],
                               Path(cfg.run_dir))
                bus = Bus.open(connect=connect, mode="client")
                feeder = None
                try:
                    meter = StepMeter(cfg.run_id)
                    bus.subscribe(keys.status_all(cfg.run_id), meter.on_status)
                    feeder = _Repeater(self._learner(cfg, bus).publish_params, 0.5)
                    steps = meter.measure(n, self.cfg.warmup_s, self.cfg.measure_s, self.cfg.start_timeout_s,
                                          self.check)
                    rates = meter.window_rates
                    qps = {key.split("/")[1]: v for key, v in rates.items() if key.endswith("/rows")}
                    busy = {key.split("/")[1]: v for key, v in rates.items() if key.endswith("/busy_s")}
                finally:
                    if feeder is not None:
                        feeder.stop()
                    bus.close()
                    self.stop_all()
                out.setdefault(str(k), {})[str(n)] = {
                    "actor_env_steps_per_s": steps, "qps_served": sum(qps.values()), "qps_per_shard": qps,
                    # seconds busy per second; QPs/s at 100% busy = a shard core's capacity at this batch
                    "shield_busy_share": busy,
                    "qps_per_busy_shard_s": {s_: qps[s_] / busy[s_] for s_ in qps if busy.get(s_)}}
        return out

    # ------------------------------------------------------------- all
    def measure_physics_bound(self) -> float:
        """The one-core raw physics bound of the actors' batch (``sage bench env``'s
        ``raw_physics_env_steps_per_s``), measured now."""
        raw = bench_env(self.cfg.scenario, num_envs=self.cfg.envs_per_actor, steps=50, seed=self.cfg.seed)
        return float(raw["raw_physics_env_steps_per_s"])

    def run(self) -> dict:
        t0 = time.monotonic()
        out = {"bench": "system", "config": asdict(self.cfg),
               "host": {"cpus": host_cpus()}}
        try:
            # the bound at the start (each system phase measures its own around it)
            out["physics_bound_env_steps_per_s"] = self.measure_physics_bound()
            out.update(self.services_phase())
            out["ratio_target"] = RATIO_TARGET
            out["meets_target"] = bool(out["ratio_vs_local_qp"] >= RATIO_TARGET)
            out["system"] = {m: self.system_phase(m) for m in self.cfg.methods}
            out["shards"] = self.shards_phase()
        finally:
            self.stop_all()
        out["wall_s"] = time.monotonic() - t0
        return out


class _Repeater:
    """Call ``fn`` every ``period`` seconds on a thread until stopped."""

    def __init__(self, fn, period: float):
        self._stop = threading.Event()
        self._fn, self._period = fn, period
        self._thread = threading.Thread(target=self._loop, daemon=True)
        self._thread.start()

    def _loop(self):
        while not self._stop.is_set():
            self._fn()
            self._stop.wait(self._period)

    def stop(self):
        self._stop.set()
        self._thread.join(5)


# ----------------------------------------------------------------- command line
def register(commands, bench) -> None:
    d = SystemBenchConfig()
    p = bench.add_parser("system", help="distributed throughput/latency vs in-process (shield RTT, params, steps/s)")
    p.add_argument("--json", action="store_true", help="print the result as JSON (default: a short table)")
    p.add_argument("--quick", action="store_true", help="smallest run (CI smoke): 1 actor, 2 batch sizes, 2 s windows")
    p.add_argument("--scenario", default=d.scenario, choices=sorted(SCENARIOS))
    p.add_argument("--method", default=d.method, choices=METHODS, help="method of the shield/actor phases")
    p.add_argument("--methods", default=",".join(d.methods), help="methods of the whole-system phases, e.g. happo,sage")
    p.add_argument("--shards", default=",".join(map(str, d.shard_counts)), help="shield shard counts, e.g. 1,2")
    p.add_argument("--shard-actors", default=",".join(map(str, d.shard_actor_counts)),
                   help="actor counts of the shard phase, e.g. 2,4")
    p.add_argument("--envs-per-actor", type=positive_int, default=d.envs_per_actor)
    p.add_argument("--actors", default=",".join(map(str, d.actor_counts)), help="actor counts, e.g. 1,2")
    p.add_argument("--batch-sizes", default=",".join(map(str, d.batch_sizes)))
    p.add_argument("--seconds", type=positive_float, default=d.measure_s,
                   help="steady-state window per throughput figure")
    p.add_argument("--work-dir", default=None, help="keep run dirs and service logs here (default: a temp dir)")
    p.add_argument("--out", default=None, help="also write the JSON to this file")
    p.set_defaults(func=cmd_bench_system)


def config_from_args(args) -> SystemBenchConfig:
    cfg = SystemBenchConfig(scenario=args.scenario, method=args.method, envs_per_actor=args.envs_per_actor,
                            actor_counts=tuple(int_list(args.actors, minimum=1, name="--actors")),
                            methods=tuple(m.strip() for m in args.methods.split(",") if m.strip()),
                            shard_counts=tuple(int_list(args.shards, minimum=1, name="--shards")),
                            shard_actor_counts=tuple(int_list(args.shard_actors, minimum=1, name="--shard-actors")),
                            batch_sizes=tuple(int_list(args.batch_sizes, minimum=1, name="--batch-sizes")),
                            measure_s=args.seconds)
    if args.quick:
        cfg = replace(cfg, **QUICK)
    return cfg.validate()


def cmd_bench_system(args) -> int:
    with user_input():
        cfg = config_from_args(args)
    if args.work_dir and Path(args.work_dir).exists() and not Path(args.work_dir).is_dir():
        raise UsageError(f"--work-dir {args.work_dir} exists and is not a directory")
    if args.out and Path(args.out).is_dir():
        raise UsageError(f"--out {args.out} is a directory; give a file name")
    work = Path(args.work_dir) if args.work_dir else Path(tempfile.mkdtemp(prefix="sage-bench-system-"))
    result = SystemBench(cfg, work).run()
    result["work_dir"] = str(work)
    text = json.dumps(result, indent=2)
    if args.out:
        Path(args.out).write_text(text + "\n")
    if args.json:
        print(text)
    else:
        print(summary_table(result))
    return 0


def _share(x) -> str:
    return f"{x:5.2f}" if x is not None else "    -"


def summary_table(r: dict) -> str:
    lines = [f"raw physics bound (1 core): {r['physics_bound_env_steps_per_s']:.0f} env steps/s at the start",
             "env steps/s            multi-process (x bound, learner busy)   in-process (x bound, learner busy)"]
    for method, by_n in r["system"].items():
        first = next(iter(by_n.values()), {})
        if "physics_bound_before" in first:
            lines.append(f"  {method}: physics bound {first['physics_bound_before']:.0f} before, "
                         f"{first['physics_bound_after']:.0f} after its phase; ratios to the mean")
        for n, v in by_n.items():
            note = f"   restarts {v['restarts']}" if v.get("restarts") else ""
            note += f"   in-process failures {v['inprocess_failures']}" if v.get("inprocess_failures") else ""
            lines.append(f"  {method:<9} {n} actor(s) {v['multiprocess']:9.1f} ({v['multiprocess_ratio_to_physics_bound']:.2f}, "
                         f"{_share(v['learner_update_share'])})      {v['inprocess']:9.1f} "
                         f"({v['inprocess_ratio_to_physics_bound']:.2f}, {_share(v['inprocess_learner_update_share'])})"
                         f"{note}")
            for where, budget in (("multi-process", v.get("cpu")), ("in-process", v.get("inprocess_cpu"))):
                if budget:
                    parts = ", ".join(f"{k} {us:.0f}" for k, us in budget["core_us_per_env_step"].items())
                    lines.append(f"      {where} core-us per env step: {parts}; total "
                                 f"{budget['core_us_per_env_step_total']:.0f} -> the host's cores allow "
                                 f"{budget['cpu_bound_env_steps_per_s']:.0f} "
                                 f"({budget['cpu_bound_ratio_to_physics_bound']:.2f} x bound)")
    lines.append("shield shards          actor env steps/s   QPs/s served")
    for k, by_n in r["shards"].items():
        for n, v in by_n.items():
            lines.append(f"  {k} shard(s), {n} actors {v['actor_env_steps_per_s']:12.1f} {v['qps_served']:12.1f}")
    lines.append("shield RTT ms     p50 / p99 (process)   p50 / p99 (in-process)   local QP p50 / p99"
                 "   pruned p50 / p99   bytes full / pruned")
    for B, v in r["shield_rtt_ms"].items():
        lines.append(f"  B={B:<5}        {v['p50']:7.3f} / {v['p99']:7.3f}     {v['inprocess_p50']:7.3f} / "
                     f"{v['inprocess_p99']:7.3f}        {v['local_qp_p50']:7.3f} / {v['local_qp_p99']:7.3f}"
                     f"   {v['pruned_p50']:7.3f} / {v['pruned_p99']:7.3f}   {v['bytes']} / {v['pruned_bytes']}")
    pb = r["param_broadcast_ms"]
    lines.append(f"param broadcast   p50 {pb['p50']:.3f} ms  p99 {pb['p99']:.3f} ms  "
                 f"(in-process {pb['inprocess_p50']:.3f} / {pb['inprocess_p99']:.3f}; {pb['bytes']} B)")
    a = r["actor_steps_per_s"]
    lines.append(f"one actor steps/s: shield service {a['shield_service']:.1f} (pipelined "
                 f"{a['shield_service_pipelined']:.1f}, full rows {a['shield_service_full_rows']:.1f}), "
                 f"local QP {a['local_qp']:.1f}, ratio {r['ratio_vs_local_qp']:.2f} (target >= {r['ratio_target']})")
    cost = r.get("actor_core_us_per_env_step") or {}
    if cost.get("shield_service", {}).get("host") and cost.get("local_qp", {}).get("host"):
        lines.append(f"one actor, core-us per env step (actor process / with router and shield): shield service "
                     f"{cost['shield_service']['actor']:.0f} / {cost['shield_service']['host']:.0f}, local QP "
                     f"{cost['local_qp']['actor']:.0f} / {cost['local_qp']['host']:.0f}; "
                     f"CPU ratio {r['cpu_ratio_vs_local_qp']:.2f}")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    if argv and argv[0] == "local-actor":
        return run_entry("actor", LocalQPActor, argv[1:])
    if argv and argv[0] == "echo":
        return echo_main(argv[1:])
    print("usage: python -m sage.bench.system {local-actor|echo} ... (the benchmark is `sage bench system`)",
          file=sys.stderr)
    return 2


if __name__ == "__main__":
    sys.exit(main())
