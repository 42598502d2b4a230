"""The thread placement: every member of a run a thread of this process, all on
one network-less Zenoh session (``sage train``'s default, and CI's). The run
driver (``deploy/driver.py``) writes the records (``supervisor.jsonl``,
``status.json``), shows the live line, decides the outcome and shuts down, as it
does for local processes and Ray; this placement says only that a member is a
thread (``services.launcher.ServiceThreads``) and that a thread cannot be
restarted: a member that raises ends the run (``CheckpointError``: exit 4 and its
one line, as a process would; anything else: exit 1 and the error).
"""
from __future__ import annotations

import io
import logging
import threading
import time
from dataclasses import dataclass
from pathlib import Path

from prometheus_client import CollectorRegistry

from common.checkpoint import CheckpointError
from common.metrics_prom import serve_metrics
from common.status import EXIT_FATAL, StatusBoard
from common.transport import Bus
from deploy.driver import EXIT_GAVE_UP, Member, RunDriver
from services.base import Service
from services.config import TrainConfig
from services.launcher import SERVICE_CLASSES, ServiceThreads, run_members

log = logging.getLogger("sage.threads")


@dataclass
class ThreadsConfig:
    poll_s: float = 0.2                # the loop waits this long on the learner's thread
    status_period_s: float = 1.0       # live line and status.json refresh
    status_log_period_s: float = 10.0  # when stderr is not a terminal: one status line this often
    join_timeout_s: float = 10.0       # a stopped service's thread gets this long to return


@dataclass(frozen=True)
class ThreadSpec:
    """What the driver needs to know of a member (``deploy.supervisor.ServiceSpec`` without a command)."""
    name: str                          # the service's sender: "learner/0", "actor/1", "shield/0"
    ends_run: bool = False
    stop_wave: int = 0
    ready_tcp: tuple[str, int] | None = None


class _ThreadMember(Member):
    def __init__(self, svc: Service):
        super().__init__(ThreadSpec(svc.sender, ends_run=svc.sender.startswith("learner/")))
        self.svc = svc


class ThreadPlacement(RunDriver):
    """The members of ``services`` (sender -> service, all on one stop event) as
    threads; ``timeout_s`` ends the run with exit 1 (tests)."""

    label = member_word = "threads"

    def __init__(self, services: dict[str, Service], stop: threading.Event, run_dir: str | Path,
                 cfg: ThreadsConfig | None = None, *, timeout_s: float | None = None, out=None):
        super().__init__([_ThreadMember(s) for s in services.values()], run_dir, cfg or ThreadsConfig(), out=out)
        self.group = ServiceThreads(stop)
        self.timeout_s = timeout_s
        self.t0 = time.monotonic()
        self.failure: tuple[str, BaseException] | None = None   # the first service that raised
        self.timed_out = False

    def start(self) -> None:
        self.t0 = time.monotonic()
        for m in self.members:
            self.group.start(m.svc)
            m.state, m.starts = "running", 1
            self.event("start", service=m.spec.name, attempt=1)

    def poll_members(self) -> None:
        for m in self.members:
            if m.state != "running" or self.group.threads[m.spec.name].is_alive():
                continue
            err = next((exc for who, exc in self.group.errors if who == m.spec.name), None)
            m.last_code = (EXIT_FATAL if isinstance(err, CheckpointError) else EXIT_GAVE_UP) if err is not None \
                else self.group.codes.get(m.spec.name, 0)
            m.state = "failed" if err is not None else "done"
            self.event("exit", service=m.spec.name, code=m.last_code, **({"error": repr(err)} if err else {}))
            if err is not None:
                self.failure = self.failure or (m.spec.name, err)
                self.finish(m.last_code, f"{m.spec.name}: {err}" if m.last_code == EXIT_FATAL
                            else f"service {m.spec.name} failed: {err!r}")
            elif m.spec.ends_run:
                self.finish(0, f"{m.spec.name} finished")
        if self.outcome is None and self.timeout_s is not None and time.monotonic() - self.t0 > self.timeout_s:
            self.timed_out = True
            self.finish(EXIT_GAVE_UP, f"in-process run exceeded {self.timeout_s} s")

    def idle(self) -> None:
        learner = self.group.threads.get("learner/0")
        if learner is not None and learner.is_alive():
            learner.join(self.cfg.poll_s)
        else:
            time.sleep(self.cfg.poll_s)

    def final_line(self, status: StatusBoard | None) -> str | None:
        """The learner's own final counters: its last heartbeat may still be in flight."""
        learner = next(m.svc for m in self.members if m.spec.ends_run)
        own = {learner.sender: {"role": "learner", "state": learner.state, **learner.status_fields()}}
        return status.line(own) if status is not None else None

    def stop_wave(self, group: list[Member]) -> None:
        self.group.stop.set()          # one stop event for the whole process
        for m in group:
            t = self.group.threads.get(m.spec.name)
            if t is not None:
                t.join(self.cfg.join_timeout_s)
            if m.state == "running":
                m.state = "stopped" if t is None or not t.is_alive() else "running"
                self.event("stop", service=m.spec.name, alive=bool(t is not None and t.is_alive()))


def build_services(cfg: TrainConfig, bus: Bus, registry: CollectorRegistry, stop: threading.Event, *,
                   method=None, envs=None, propose=None, solve=None) -> dict[str, Service]:
    """Every member of the run as a service on ``bus`` (sender -> service);
    ``method``, ``envs`` (one per actor), ``propose`` and ``solve`` replace the
    real components (tests)."""
    services: dict[str, Service] = {}
    for m in run_members(range(cfg.actors), shields=cfg.shields):
        kw = {"shield": {"solve": solve}, "learner": {"method": method}}.get(m.role, {})
        if m.role == "actor":
            kw = {"env": envs[m.member_id] if envs else None, "propose": propose}
        services[m.sender] = SERVICE_CLASSES[m.role](cfg, bus, m.member_id, registry, stop, **kw)
    return services


def run_inprocess(cfg: TrainConfig, *, progress: bool = True, method=None, envs=None,
                  propose=None, solve=None, registry: CollectorRegistry | None = None,
                  timeout_s: float | None = None, out=None) -> dict:
    """Run a whole training job as threads of this process under the run driver;
    returns the learner summary (``exit_code`` 0, or 128 + signal when a signal
    stopped it). A service that raised raises here: ``SystemExit`` with its one
    line for a ``CheckpointError``, ``RuntimeError`` otherwise; ``timeout_s``:
    ``TimeoutError``."""
    registry = registry if registry is not None else CollectorRegistry()
    server = serve_metrics(cfg.ports.inprocess, registry, addr=cfg.ports.bind)
    bus = Bus.open(inprocess=True)
    stop = threading.Event()
    try:
        services = build_services(cfg, bus, registry, stop, method=method, envs=envs, propose=propose, solve=solve)
        learner = services["learner/0"]
        board = StatusBoard(cfg.run_id, stale_after_s=max(5.0, 5 * cfg.status_period_s)).attach(bus)
        driver = ThreadPlacement(services, stop, cfg.run_dir, ThreadsConfig(status_period_s=cfg.status_period_s),
                                 timeout_s=timeout_s, out=out if progress else io.StringIO())
        code = driver.run(lambda: board, install_signals=threading.current_thread() is threading.main_thread())
    finally:
        bus.close()
        if server is not None:
            server.shutdown()
    if driver.timed_out:
        raise TimeoutError(f"in-process run exceeded {timeout_s} s")
    if driver.failure is not None:
        name, exc = driver.failure
        if isinstance(exc, CheckpointError):   # a fault restarting cannot fix: one line, non-zero exit
            raise SystemExit(f"{name}: {exc}")
        raise RuntimeError(f"service {name} failed: {exc!r}") from exc
    actors = [s for k, s in services.items() if k.startswith("actor/")]
    shields = [s for k, s in services.items() if k.startswith("shield/")]
    result = learner.summary()
    result["exit_code"] = code
    result["actor_codes"] = {k: v for k, v in driver.group.codes.items() if k.startswith("actor/")}
    result["status"] = board.members()
    result["actors"] = [{"env_steps": a.env_steps, "shield_failures": a.shield_failures,
                         "chunks": a.chunks_sent, "rejected": dict(a.rejected)} for a in actors]
    result["shields"] = [{"requests": sh.n_requests, "rows": sh.n_rows, "p50_s": sh.solve_window.quantile(0.5),
                          "p99_s": sh.solve_window.quantile(0.99)} for sh in shields]
    result["params"] = learner.method.policy_params() if learner.method is not None else None
    return result
