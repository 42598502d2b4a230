"""What every service loop shares: identity, metrics labels, message
encode/decode with counted rejections, status heartbeats, the stop event,
and the process entry-point plumbing (config file, signals, Zenoh session)."""
from __future__ import annotations

import argparse
import ctypes
import logging
import os
import signal
import threading
import time
from collections import defaultdict, deque

from prometheus_client import CollectorRegistry

from common import keys, wire
from common.checkpoint import CheckpointError
from common.metrics_prom import SageMetrics, serve_metrics
from common.status import EXIT_FATAL
from common.transport import Bus
from services.config import TrainConfig

log = logging.getLogger("sage.services")


class Service:
    role = "service"

    def __init__(self, cfg: TrainConfig, bus: Bus, member_id: int | str = 0,
                 registry: CollectorRegistry | None = None, stop: threading.Event | None = None):
        self.cfg = cfg
        self.bus = bus
        self.member_id = str(member_id)
        self.sender = f"{self.role}/{self.member_id}"
        self.registry = registry if registry is not None else CollectorRegistry()
        self.m = SageMetrics.for_registry(self.registry)
        self.labels = {"role": self.role, "actor_id": self.member_id if self.role == "actor" else ""}
        self.stop = stop if stop is not None else threading.Event()
        self._seq: dict[str, int] = defaultdict(int)
        self._t0 = time.monotonic()
        self._last_status = -1e9
        self.rejected: dict[str, int] = defaultdict(int)  # reason -> count (also in Prometheus)
        self.state = "starting"
        self.log = logging.getLogger(f"sage.{self.role}.{self.member_id}")
        self._max_message_bytes = cfg.message_bytes_bound()
        self._big_freed = False

    # ------------------------------------------------------------- messages
    def encode(self, kind: str, body: dict) -> bytes:
        seq = self._seq[kind]
        self._seq[kind] += 1
        return wire.encode(kind, body, run_id=self.cfg.run_id, sender=self.sender, seq=seq)

    def send(self, key: str, kind: str, body: dict) -> None:
        self.bus.publish(key, self.encode(kind, body))

    def decode(self, payload: bytes, expect, bounds: dict[str, int] | None = None) -> wire.Message | None:
        """Decode or count-and-log the rejection; never raises. ``bounds``:
        ``wire.decode``'s per-run caps on shape symbols."""
        unexpected = None
        if len(payload) >= _TRIM_AFTER_BYTES:
            self._big_freed = True   # its buffers are released at the next status tick (release_memory)
        try:
            msg = wire.decode(payload, run_id=self.cfg.run_id, expect=expect, bounds=bounds,
                              max_bytes=self._max_message_bytes)
        except wire.WireError as exc:
            reason, detail = exc.reason, exc.detail
        except Exception as exc:  # noqa: BLE001 - defence in depth: no message may kill the loop
            reason, detail, unexpected = "malformed", f"{type(exc).__name__}: {str(exc)[:200]}", exc
        else:
            self.m.received.labels(**self.labels, kind=msg.kind).inc()
            return msg
        self.rejected[reason] += 1
        self.m.rejected.labels(**self.labels, reason=reason).inc()
        n = self.rejected[reason]
        if n <= 3 or n % 100 == 0:  # log the first few and then every 100th
            self.log.warning("rejected message (%s, #%d): %s", reason, n, detail,
                             exc_info=unexpected)  # a decoder bug: keep its traceback
        return None

    # ------------------------------------------------------------- status / control
    def status_fields(self) -> dict:
        """Role-specific status fields; overridden by services."""
        return {}

    def publish_status(self, force: bool = False, message: str = "") -> None:
        now = time.monotonic()
        if not force and now - self._last_status < self.cfg.status_period_s:
            return
        self._last_status = now
        if self._big_freed:
            self._big_freed = False
            release_memory()
        body = {"role": self.role, "id": self.member_id, "state": self.state, "pid": os.getpid(),
                "uptime_s": now - self._t0, "version": -1, "env_steps": 0, "env_steps_per_s": 0.0,
                "updates": 0, "success_rate": None, "shield_p99_s": None, "message": message,
                "extra": {}}
        body.update(self.status_fields())
        if message:
            body["message"] = message
        self.send(keys.status(self.cfg.run_id, self.role, self.member_id), "status", body)

    def listen_control(self) -> None:
        def on_control(_key: str, payload: bytes) -> None:
            msg = self.decode(payload, "control")
            if msg is None:
                return
            target = msg.body["target"]
            if msg.body["command"] == "stop" and target in ("*", self.role, self.sender):
                self.log.info("stop requested by %s", msg.sender)
                self.stop.set()

        self.bus.subscribe(keys.control(self.cfg.run_id), on_control)


_TRIM_AFTER_BYTES = 1 << 20   # a message this large marks heap memory to hand back (release_memory)


def release_memory() -> None:
    """Hand freed heap memory back to the OS (glibc ``malloc_trim``): large message
    buffers freed by Python stay in the process's heap otherwise, and its RSS keeps
    the peak of the largest messages ever received. A no-op off glibc."""
    global _malloc_trim
    if _malloc_trim is None:
        try:
            _malloc_trim = ctypes.CDLL("libc.so.6").malloc_trim
        except (OSError, AttributeError):
            _malloc_trim = False
    if _malloc_trim:
        _malloc_trim(0)


_malloc_trim = None


class RateMeter:
    """Events per second over a sliding window of (time, count) samples."""

    def __init__(self, window_s: float = 10.0):
        self.window_s = window_s
        self._d: deque[tuple[float, int]] = deque()

    def add(self, total: int) -> None:
        now = time.monotonic()
        self._d.append((now, total))
        while len(self._d) > 2 and now - self._d[0][0] > self.window_s:
            self._d.popleft()

    def rate(self) -> float:
        if len(self._d) < 2:
            return 0.0
        (t0, n0), (t1, n1) = self._d[0], self._d[-1]
        return (n1 - n0) / (t1 - t0) if t1 > t0 else 0.0


# ----------------------------------------------------------------- entry points
def metrics_port(cfg: TrainConfig, role: str, member_id: int) -> int:
    """Prometheus port of a member (0 = off): the learner's, shield shard k at
    ``ports.shield + k``, actor i at ``ports.actor_base + i``."""
    base = {"learner": cfg.ports.learner, "shield": cfg.ports.shield, "actor": cfg.ports.actor_base}[role]
    return base + int(member_id) if base and role != "learner" else base


def entry_parser(role: str) -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog=f"python -m services.{role}", description=f"SAGE {role} service")
    p.add_argument("--config", required=True, help="resolved run config (RUN.json)")
    if role == "actor":
        p.add_argument("--actor-id", type=int, required=True)
    if role == "shield":
        p.add_argument("--shard", type=int, default=0, help="shield shard k (0 .. shields-1), key shield/<k>")
    p.add_argument("--log-level", default="INFO")
    return p


def run_entry(role: str, make_service, argv=None) -> int:
    """Parse args, install signal handlers, open the Zenoh session (after start,
    never inherited through fork), run the service loop, close cleanly."""
    args = entry_parser(role).parse_args(argv)
    logging.basicConfig(level=args.log_level, format=f"%(asctime)s {role} %(levelname)s %(name)s: %(message)s")
    cfg = TrainConfig.load(args.config)
    stop = threading.Event()

    def on_signal(signum, _frame):
        log.info("signal %d: stopping", signum)
        stop.set()

    signal.signal(signal.SIGTERM, on_signal)
    signal.signal(signal.SIGINT, on_signal)
    registry = CollectorRegistry()
    member = getattr(args, "actor_id", getattr(args, "shard", 0))
    port = metrics_port(cfg, role, member)
    server = serve_metrics(port, registry, addr=cfg.ports.bind)
    mode = cfg.transport.mode
    if mode == "peer" and cfg.transport.connect and not cfg.transport.listen:
        # A peer with gossip off that only dials a router does not get its
        # partners' publications routed to it; as a client it does.
        mode = "client"
    # TLS identity of this role, if configured; Zenoh refuses messages past the run's bound
    # (an actor uses its own certificate, actor-<id>, where the run has per-actor ones)
    bus = Bus.from_transport(cfg.transport, role=role, mode=mode, max_message_bytes=cfg.message_bytes_bound(),
                             member=member if role == "actor" else None)
    try:
        service = make_service(cfg, bus, member, registry, stop)
        try:
            return int(service.run() or 0)
        except CheckpointError as exc:   # restarting cannot fix it: one line, and the run stops
            log.error("%s", exc)
            return EXIT_FATAL
    finally:
        bus.close()
        if server is not None:
            server.shutdown()
