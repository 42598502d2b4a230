"""Prometheus metrics of the SAGE services (names in docs/wire.md).

Convention: ``sage_`` prefix, base units (seconds), ``_total`` counters,
labels ``role`` and ``actor_id`` on everything so that the in-process mode can
put all services in one registry. ``SageMetrics.for_registry`` returns one
shared instance per registry (prometheus-client refuses duplicate names).
"""
from __future__ import annotations

import threading
from collections import deque

import numpy as np
from prometheus_client import CollectorRegistry, Counter, Gauge, Histogram, start_http_server

# 1 µs .. 10 s, roughly x2.5 per bucket: QP solves are µs, round trips ms
LATENCY_BUCKETS = (1e-6, 2.5e-6, 5e-6, 1e-5, 2.5e-5, 5e-5, 1e-4, 2.5e-4, 5e-4, 1e-3,
                   2.5e-3, 5e-3, 1e-2, 2.5e-2, 5e-2, 0.1, 0.25, 0.5, 1.0, 2.5, 5.0, 10.0)
BATCH_BUCKETS = (1, 2, 4, 8, 16, 32, 64, 128, 256, 512, 1024)
NORM_BUCKETS = (0.0, 1e-4, 1e-3, 1e-2, 0.03, 0.1, 0.3, 1.0, 3.0)

_L = ("role", "actor_id")


class SageMetrics:
    _instances: dict[int, "SageMetrics"] = {}
    _lock = threading.Lock()

    @classmethod
    def for_registry(cls, registry: CollectorRegistry) -> "SageMetrics":
        with cls._lock:
            inst = cls._instances.get(id(registry))
            if inst is None or inst.registry is not registry:
                inst = cls(registry)
                cls._instances[id(registry)] = inst
            return inst

    def __init__(self, registry: CollectorRegistry):
        r = self.registry = registry
        self.received = Counter("sage_messages_received_total", "Messages decoded and accepted",
                                _L + ("kind",), registry=r)
        self.rejected = Counter("sage_messages_rejected_total", "Messages rejected by the wire decoder",
                                _L + ("reason",), registry=r)
        self.shield_requests = Counter("sage_shield_requests_total", "Shield queries received", _L, registry=r)
        self.shield_queue = Gauge("sage_shield_queue_depth", "Queries waiting for a batch", _L, registry=r)
        self.shield_batch = Histogram("sage_shield_batch_size", "QP rows per solve_cbf_qp call", _L,
                                      buckets=BATCH_BUCKETS, registry=r)
        self.shield_solve = Histogram("sage_shield_solve_seconds", "solve_cbf_qp wall time per batch", _L,
                                      buckets=LATENCY_BUCKETS, registry=r)
        self.shield_infeasible = Counter("sage_shield_infeasible_total", "QP rows answered infeasible", _L,
                                         registry=r)
        self.shield_correction = Histogram("sage_shield_correction_norm", "||a_exec - a_prop|| per row", _L,
                                           buckets=NORM_BUCKETS, registry=r)
        self.shield_errors = Counter("sage_shield_errors_total", "Queries answered with reply_err",
                                     _L + ("reason",), registry=r)
        self.env_steps = Counter("sage_actor_env_steps_total", "Environment steps (all K envs)", _L, registry=r)
        self.roundtrip = Histogram("sage_actor_shield_roundtrip_seconds", "Shield query round trip", _L,
                                   buckets=LATENCY_BUCKETS, registry=r)
        self.shield_timeouts = Counter("sage_actor_shield_timeouts_total",
                                       "Shield queries unanswered in time (nothing executed)", _L, registry=r)
        self.answers_rejected = Counter("sage_actor_shield_answers_rejected_total",
                                        "Shield answers that failed the actor's own check (never executed)",
                                        _L + ("reason",), registry=r)
        self.params_rejected = Counter("sage_actor_params_rejected_total",
                                       "Parameter messages that failed the tree-shape check (not adopted)",
                                       _L, registry=r)
        self.dropped = Counter("sage_queue_dropped_total", "Items dropped by a full bounded queue",
                               _L + ("queue",), registry=r)
        self.healthy = Gauge("sage_actor_healthy", "1 healthy, 0 unhealthy", _L, registry=r)
        self.version = Gauge("sage_param_version", "Parameter version held/published", _L, registry=r)
        self.episodes = Counter("sage_episodes_total", "Finished episodes", _L, registry=r)
        self.success_rate = Gauge("sage_success_rate", "Success rate of recent episodes", _L, registry=r)
        self.updates = Counter("sage_learner_updates_total", "Method updates", _L, registry=r)
        self.update_seconds = Histogram("sage_learner_update_seconds", "Method.update wall time", _L,
                                        buckets=LATENCY_BUCKETS, registry=r)
        self.chunks = Counter("sage_learner_chunks_total", "Trajectory chunks by outcome",
                              _L + ("outcome",), registry=r)


DEFAULT_BIND = "127.0.0.1"   # metrics are not for the whole network unless asked (PortsConfig.bind)


def serve_metrics(port: int | None, registry: CollectorRegistry, addr: str | None = DEFAULT_BIND):
    """Expose ``registry`` on ``addr:port``; 0/None port disables. Returns the
    server or None. ``addr`` defaults to loopback (prometheus_client's own
    default is 0.0.0.0): pass ``PortsConfig.bind`` ("0.0.0.0", "::" or one
    interface's address) to let a Prometheus on another host scrape it."""
    if not port:
        return None
    server, _thread = start_http_server(int(port), addr=addr or DEFAULT_BIND, registry=registry)
    return server


class Window:
    """Recent samples for quantiles shown in status messages (thread-safe)."""

    def __init__(self, size: int = 2000):
        self._d: deque[float] = deque(maxlen=size)
        self._lock = threading.Lock()

    def add(self, x: float) -> None:
        with self._lock:
            self._d.append(float(x))

    def quantile(self, q: float) -> float | None:
        with self._lock:
            if not self._d:
                return None
            return float(np.quantile(np.fromiter(self._d, float), q))

    def mean(self) -> float | None:
        with self._lock:
            return float(np.mean(self._d)) if self._d else None
