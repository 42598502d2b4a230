"""Thin Zenoh layer: bytes in, bytes out (publish/subscribe, queryable/get).

The services only use ``Bus``; swapping Zenoh for another transport means
reimplementing this file. Payloads are opaque bytes (``common/wire.py``).

In-process mode (``Bus.open(inprocess=True)``) is a real Zenoh peer session
with no network: multicast and gossip scouting off, no listen and no connect
endpoints. All services then run as threads on that one session, and Zenoh
delivers publications and queries locally.
"""
from __future__ import annotations

import json
import logging
import queue
import threading
import time
from dataclasses import dataclass
from typing import Callable, Sequence

import zenoh

log = logging.getLogger(__name__)


def zenoh_config(*, connect: Sequence[str] = (), listen: Sequence[str] = (),
                 mode: str = "peer", multicast_scouting: bool = False) -> zenoh.Config:
    """Zenoh config with explicit endpoints only.

    Multicast scouting is off by default so a process never attaches to a
    stranger's network by accident; multi-host runs list a router in
    ``connect`` (docs/wire.md, deploy/).
    """
    if mode not in ("peer", "client", "router"):
        raise ValueError(f"zenoh mode {mode!r}")
    cfg = zenoh.Config()
    cfg.insert_json5("mode", json.dumps(mode))
    cfg.insert_json5("scouting/multicast/enabled", json.dumps(bool(multicast_scouting)))
    cfg.insert_json5("scouting/gossip/enabled", json.dumps(bool(multicast_scouting)))
    cfg.insert_json5("connect/endpoints", json.dumps(list(connect)))
    cfg.insert_json5("listen/endpoints", json.dumps(list(listen)))
    return cfg


@dataclass
class Reply:
    ok: bytes | None = None
    err: bytes | None = None


class Request:
    """One received query; the owner must call exactly one of ``reply`` /
    ``reply_err``, then ``finish`` (also done by both reply methods)."""

    __slots__ = ("_query", "_key", "payload", "t_recv")

    def __init__(self, query: zenoh.Query, payload: bytes, t_recv: float):
        self._query = query
        self._key = query.key_expr
        self.payload = payload
        self.t_recv = t_recv

    def reply(self, payload: bytes) -> None:
        try:
            self._query.reply(self._key, payload)
        finally:
            self.finish()

    def reply_err(self, payload: bytes) -> None:
        try:
            self._query.reply_err(payload)
        finally:
            self.finish()

    def finish(self) -> None:
        """Finalize the query so the asker's get() completes (idempotent)."""
        q, self._query = self._query, None
        if q is not None:
            q.drop()


class Bus:
    """A Zenoh session with the four operations the services need."""

    def __init__(self, session: zenoh.Session):
        self._session = session
        self._publishers: dict[str, zenoh.Publisher] = {}
        self._entities: list = []
        self._lock = threading.Lock()
        self._closed = False

    @classmethod
    def open(cls, *, connect: Sequence[str] = (), listen: Sequence[str] = (),
             mode: str = "peer", inprocess: bool = False) -> "Bus":
        if inprocess:
            connect, listen = (), ()
        return cls(zenoh.open(zenoh_config(connect=connect, listen=listen, mode=mode)))

    # ------------------------------------------------------------- pub/sub
    def publish(self, key: str, payload: bytes) -> None:
        with self._lock:
            if self._closed:
                return
            pub = self._publishers.get(key)
            if pub is None:
                pub = self._session.declare_publisher(key)
                self._publishers[key] = pub
        pub.put(payload)

    def subscribe(self, key: str, callback: Callable[[str, bytes], None]) -> None:
        """``callback(key, payload)`` runs on a Zenoh thread: keep it short
        (decode + hand over to a queue); exceptions are logged, never raised."""

        def _cb(sample: zenoh.Sample) -> None:
            try:
                callback(str(sample.key_expr), sample.payload.to_bytes())
            except Exception:  # a bad message must never kill Zenoh's thread
                log.exception("subscriber callback on %s failed", key)

        with self._lock:
            self._entities.append(self._session.declare_subscriber(key, _cb))

    # ------------------------------------------------------------- query
    def serve(self, key: str) -> "queue.Queue[Request]":
        """Declare a queryable; received queries land in the returned queue."""
        q: queue.Queue[Request] = queue.Queue()

        def _cb(query: zenoh.Query) -> None:
            payload = query.payload.to_bytes() if query.payload is not None else b""
            q.put(Request(query, payload, time.perf_counter()))

        with self._lock:
            self._entities.append(self._session.declare_queryable(key, _cb))
        return q

    def request(self, key: str, payload: bytes, timeout: float) -> Reply | None:
        """One get; the first reply, or None when nobody answered in time."""
        replies = self._session.get(key, payload=payload, timeout=float(timeout))
        for r in replies:  # iteration ends when the query is finalized or times out
            if r.ok is not None:
                return Reply(ok=r.ok.payload.to_bytes())
            return Reply(err=r.err.payload.to_bytes())
        return None

    def close(self) -> None:
        with self._lock:
            if self._closed:
                return
            self._closed = True
            ents = list(self._publishers.values()) + self._entities
            self._publishers.clear()
            self._entities.clear()
        for e in ents:
            try:
                e.undeclare()
            except Exception:
                pass
        self._session.close()
