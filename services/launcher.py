"""The one launcher of a run's services: which members a run has, how each is
built, and where it runs. As in Sample Factory, the serial and the parallel
runner differ only in placement, never in what the services do:

* threads of this process on one network-less Zenoh session
  (``run_inprocess``: ``sage train``'s default and CI's), via ``ServiceThreads``;
* one process per member, each the documented entry point
  ``python -m services.<role> --config RUN.json [--actor-id I]``
  (``entry_argv``), placed and restarted by ``deploy/`` (local supervisor).

Both take the members from ``run_members`` and build each service the same
way (``SERVICE_CLASSES``).
"""
from __future__ import annotations

import logging
import sys
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

from prometheus_client import CollectorRegistry

from common.checkpoint import CheckpointError
from common.metrics_prom import serve_metrics
from common.status import LiveLine, StatusBoard
from common.transport import Bus
from services.actor.service import ActorService
from services.base import Service
from services.config import TrainConfig
from services.learner.service import LearnerService
from services.shield.service import ShieldService

log = logging.getLogger("sage.launcher")

ROLES = ("shield", "learner", "actor")
SERVICE_CLASSES: dict[str, type[Service]] = {"shield": ShieldService, "learner": LearnerService,
                                             "actor": ActorService}


@dataclass(frozen=True)
class Member:
    role: str
    member_id: int = 0

    @property
    def name(self) -> str:
        """File-safe name (logs, supervisor): ``learner``, ``actor-3``, ``shield``
        (shard 0, the only one of most runs), ``shield-2``."""
        if self.role == "actor" or (self.role == "shield" and self.member_id):
            return f"{self.role}-{self.member_id}"
        return self.role

    @property
    def sender(self) -> str:
        return f"{self.role}/{self.member_id}"


def run_members(actor_ids: Sequence[int], roles: Sequence[str] = ROLES, shields: int = 1) -> list[Member]:
    """The members of a run (or of this host's part of it), shield shards and
    learner first: actors wait for both."""
    bad = set(roles) - set(ROLES)
    if bad:
        raise ValueError(f"unknown roles {sorted(bad)}; choose from {', '.join(ROLES)}")
    out = [Member("shield", k) for k in range(shields)] if "shield" in roles else []
    out += [Member("learner")] if "learner" in roles else []
    if "actor" in roles:
        out += [Member("actor", int(i)) for i in actor_ids]
    return out


def entry_argv(member: Member, config_path: str | Path, python: str = sys.executable) -> list[str]:
    """The process entry point of ``member`` (docs/wire.md)."""
    argv = [python, "-m", f"services.{member.role}", "--config", str(config_path)]
    if member.role == "actor":
        argv += ["--actor-id", str(member.member_id)]
    elif member.role == "shield" and member.member_id:
        argv += ["--shard", str(member.member_id)]
    return argv


class ServiceThreads:
    """Services as daemon threads sharing one stop event; a service that raises
    is logged, recorded in ``errors`` and stops the others (it cannot be restarted)."""

    def __init__(self, stop: threading.Event):
        self.stop = stop
        self.threads: dict[str, threading.Thread] = {}
        self.errors: list[tuple[str, BaseException]] = []
        self.codes: dict[str, int] = {}

    def start(self, svc: Service, stop_all_on_error: bool = True) -> threading.Thread:
        def body():
            try:
                self.codes[svc.sender] = int(svc.run() or 0)
            except BaseException as exc:  # noqa: BLE001 - surfaced by failure()
                log.exception("%s failed", svc.sender)
                self.errors.append((svc.sender, exc))
                if stop_all_on_error:
                    self.stop.set()

        t = threading.Thread(target=body, name=svc.sender, daemon=True)
        self.threads[svc.sender] = t
        t.start()
        return t

    def failure(self, ignore: Sequence[str] = ()) -> tuple[str, BaseException] | None:
        return next(((who, exc) for who, exc in self.errors if who not in ignore), None)

    def join(self, timeout_s: float = 10.0) -> None:
        self.stop.set()
        for t in self.threads.values():
            t.join(timeout=timeout_s)


def run_inprocess(cfg: TrainConfig, *, progress: bool = True, method=None, envs=None,
                  propose=None, solve=None, registry: CollectorRegistry | None = None,
                  timeout_s: float | None = None, out=None) -> dict:
    """Run a whole training job as threads of this process; returns the
    learner summary. ``method``, ``envs`` (one per actor), ``propose`` and
    ``solve`` replace the real components (tests). Raises if a service failed.
    """
    registry = registry if registry is not None else CollectorRegistry()
    server = serve_metrics(cfg.ports.inprocess, registry, addr=cfg.ports.bind)
    bus = Bus.open(inprocess=True)
    stop = threading.Event()
    overrides = {"shield": {"solve": solve}, "learner": {"method": method}}
    services: dict[str, Service] = {}
    for m in run_members(range(cfg.actors), shields=cfg.shields):
        kw = overrides.get(m.role, {})
        if m.role == "actor":
            kw = {"env": envs[m.member_id] if envs else None, "propose": propose}
        services[m.sender] = SERVICE_CLASSES[m.role](cfg, bus, m.member_id, registry, stop, **kw)
    learner = services["learner/0"]
    actors = [s for k, s in services.items() if k.startswith("actor/")]
    shields = [s for k, s in services.items() if k.startswith("shield/")]
    board = StatusBoard(cfg.run_id, stale_after_s=max(5.0, 5 * cfg.status_period_s)).attach(bus)
    live = LiveLine(out if out is not None else sys.stderr)
    group = ServiceThreads(stop)
    for svc in services.values():
        group.start(svc)
    t0 = time.monotonic()
    last_line = 0.0
    try:
        learner_thread = group.threads["learner/0"]
        while learner_thread.is_alive() and not stop.is_set():
            learner_thread.join(0.2)
            if progress and time.monotonic() - last_line > 1.0:
                last_line = time.monotonic()
                live.show(board.line())
            if timeout_s is not None and time.monotonic() - t0 > timeout_s:
                raise TimeoutError(f"in-process run exceeded {timeout_s} s")
    except KeyboardInterrupt:
        log.info("interrupted: stopping services")
    finally:
        group.join()
        if progress:   # the learner's own final counters: its last heartbeat may still be in flight
            live.close(board.line({"learner/0": {"role": "learner", "state": learner.state,
                                                 **learner.status_fields()}}))
        bus.close()
        if server is not None:
            server.shutdown()
    failed = group.failure()
    if failed:
        name, exc = failed
        if isinstance(exc, CheckpointError):   # a fault restarting cannot fix: one line, non-zero exit
            raise SystemExit(f"{name}: {exc}")
        raise RuntimeError(f"service {name} failed: {exc!r}") from exc
    result = learner.summary()
    result["actor_codes"] = {k: v for k, v in group.codes.items() if k.startswith("actor/")}
    result["status"] = board.members()
    result["actors"] = [{"env_steps": a.env_steps, "shield_failures": a.shield_failures,
                         "chunks": a.chunks_sent, "rejected": dict(a.rejected)} for a in actors]
    result["shields"] = [{"requests": sh.n_requests, "rows": sh.n_rows, "p50_s": sh.solve_window.quantile(0.5),
                          "p99_s": sh.solve_window.quantile(0.99)} for sh in shields]
    result["params"] = learner.method.policy_params() if learner.method is not None else None
    return result
