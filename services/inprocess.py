"""In-process mode: shield, learner and actors as threads of one process,
talking over one Zenoh session with no network (``Bus.open(inprocess=True)``)
and sharing one Prometheus registry (members told apart by labels). The
default for ``sage train`` and for CI."""
from __future__ import annotations

import logging
import sys
import threading
import time

from prometheus_client import CollectorRegistry

from common import keys
from common.metrics_prom import serve_metrics
from common.status import status_line
from common.transport import Bus
from services.actor.service import ActorService
from services.config import TrainConfig
from services.learner.service import LearnerService
from services.shield.service import ShieldService

log = logging.getLogger("sage.inprocess")


class StatusBoard:
    """Latest status body per member, from sage/<run>/status/**."""

    def __init__(self, cfg: TrainConfig, bus: Bus, decode):
        self.latest: dict[str, dict] = {}
        self._lock = threading.Lock()
        self._decode = decode
        bus.subscribe(keys.status_all(cfg.run_id), self._on_status)

    def _on_status(self, _key: str, payload: bytes) -> None:
        msg = self._decode(payload, "status")
        if msg is not None:
            with self._lock:
                self.latest[f"{msg.body['role']}/{msg.body['id']}"] = msg.body

    def line(self) -> str:
        with self._lock:
            st = dict(self.latest)
        return status_line(st)  # in one process every member is fresh


def run_inprocess(cfg: TrainConfig, *, progress: bool = True, method=None, envs=None,
                  propose=None, solve=None, registry: CollectorRegistry | None = None,
                  timeout_s: float | None = None) -> dict:
    """Run a whole training job in this process; returns the learner summary.

    ``method``, ``envs`` (one per actor), ``propose`` and ``solve`` replace
    the real components (tests). Raises if a service thread failed.
    """
    registry = registry if registry is not None else CollectorRegistry()
    server = serve_metrics(cfg.ports.inprocess, registry)
    bus = Bus.open(inprocess=True)
    stop = threading.Event()
    shield = ShieldService(cfg, bus, 0, registry, stop, solve=solve)
    learner = LearnerService(cfg, bus, 0, registry, stop, method=method)
    actors = [ActorService(cfg, bus, i, registry, stop, env=envs[i] if envs else None, propose=propose)
              for i in range(cfg.actors)]
    board = StatusBoard(cfg, bus, learner.decode)
    errors: list[tuple[str, BaseException]] = []
    codes: dict[str, int] = {}

    def runner(svc):
        def _run():
            try:
                codes[svc.sender] = int(svc.run() or 0)
            except BaseException as exc:  # noqa: BLE001 - surfaced in the main thread
                log.exception("%s failed", svc.sender)
                errors.append((svc.sender, exc))
                stop.set()
        return threading.Thread(target=_run, name=svc.sender, daemon=True)

    threads = {svc.sender: runner(svc) for svc in [shield, learner, *actors]}
    for t in threads.values():
        t.start()
    t0 = time.monotonic()
    last_line = 0.0
    try:
        while threads["learner/0"].is_alive() and not stop.is_set():
            threads["learner/0"].join(0.2)
            if progress and time.monotonic() - last_line > 1.0:
                last_line = time.monotonic()
                sys.stderr.write("\r" + board.line() + " " * 4)
                sys.stderr.flush()
            if timeout_s is not None and time.monotonic() - t0 > timeout_s:
                raise TimeoutError(f"in-process run exceeded {timeout_s} s")
    except KeyboardInterrupt:
        log.info("interrupted: stopping services")
    finally:
        stop.set()
        for t in threads.values():
            t.join(timeout=10.0)
        if progress:
            sys.stderr.write("\r" + board.line() + "\n")
        bus.close()
        if server is not None:
            server.shutdown()
    if errors:
        name, exc = errors[0]
        raise RuntimeError(f"service {name} failed: {exc!r}") from exc
    out = learner.summary()
    out["actor_codes"] = {k: v for k, v in codes.items() if k.startswith("actor/")}
    out["status"] = board.latest
    out["actors"] = [{"env_steps": a.env_steps, "shield_failures": a.shield_failures,
                      "chunks": a.chunks_sent, "rejected": dict(a.rejected)} for a in actors]
    out["shield"] = {"requests": shield.n_requests, "rows": shield.n_rows,
                     "p50_s": shield.solve_window.quantile(0.5), "p99_s": shield.solve_window.quantile(0.99)}
    out["params"] = learner.method.policy_params() if learner.method is not None else None
    return out
