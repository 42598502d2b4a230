"""Thin Zenoh layer: bytes in, bytes out (publish/subscribe, queryable/get).

The services only use ``Bus``; swapping Zenoh for another transport means
reimplementing this file. Payloads are opaque bytes (``common/wire.py``).

In-process mode (``Bus.open(inprocess=True)``) is a real Zenoh peer session
with no network: multicast and gossip scouting off, no listen and no connect
endpoints. All services then run as threads on that one session, and Zenoh
delivers publications and queries locally.

TLS (deploy/README.md, "Secure deployment"): with ``tls_root_ca``,
``tls_cert`` and ``tls_key`` set, the session's ``transport/link/tls`` is
filled in (the CA that the router's certificate must chain to, and this
process's own client certificate for mutual TLS) and endpoints are written
``tls/<host>:<port>``. Empty fields (the default) leave the config exactly as
before: plain TCP, or no network at all in-process.
"""
from __future__ import annotations

import json
import logging
import queue
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Iterator, Sequence

import zenoh

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class TlsFiles:
    """PEM paths of one process's TLS identity. ``{role}`` in a path is
    replaced by the role (one run config, one certificate per role:
    ``certs/{role}.pem``)."""

    root_ca: str = ""
    cert: str = ""
    key: str = ""
    verify_name: bool = True   # check the router's certificate name against the endpoint's host

    @property
    def enabled(self) -> bool:
        return bool(self.root_ca or self.cert or self.key)

    def for_role(self, role: str | None, member: int | str | None = None) -> "TlsFiles":
        """The paths with ``{role}`` filled; with ``member``, ``<role>-<member>``
        where that identity's own certificate and key exist (per-actor
        certificates, deploy/tls.py ``actor_cn``), else ``<role>``."""
        if role is None:
            if "{role}" in self.cert + self.key:
                raise ValueError("TLS paths contain {role} but no role was given")
            return self
        if member is not None and "{role}" in self.cert:
            own = f"{role}-{member}"
            if Path(self.cert.replace("{role}", own)).is_file() and Path(self.key.replace("{role}", own)).is_file():
                role = own
        return TlsFiles(self.root_ca.replace("{role}", role), self.cert.replace("{role}", role),
                        self.key.replace("{role}", role), self.verify_name)

    @classmethod
    def from_transport(cls, transport) -> "TlsFiles | None":
        """From a ``services.config.TransportConfig`` (or anything with the
        ``tls_*`` attributes); None when TLS is off."""
        t = cls(getattr(transport, "tls_root_ca", "") or "", getattr(transport, "tls_cert", "") or "",
                getattr(transport, "tls_key", "") or "", bool(getattr(transport, "tls_verify_name", True)))
        return t if t.enabled else None


def tls_link_config(tls: TlsFiles, *, listen: bool = False) -> dict:
    """The ``transport/link/tls`` section for a client/peer with ``tls``.

    Fails early (FileNotFoundError) on a missing file: Zenoh would otherwise
    only log it and retry the link forever."""
    if not (tls.root_ca and tls.cert and tls.key):
        raise ValueError("TLS needs all three of root CA, certificate and private key "
                         f"(got root_ca={tls.root_ca!r}, cert={tls.cert!r}, key={tls.key!r})")
    for what, path in (("root CA", tls.root_ca), ("certificate", tls.cert), ("private key", tls.key)):
        if not Path(path).is_file():
            raise FileNotFoundError(f"TLS {what} {path} not found")
    # enable_mtls is needed on the connecting side as well: without it Zenoh
    # does not present connect_certificate and the router's handshake fails
    # with "received fatal alert: CertificateRequired" (zenoh 1.10).
    d = {"root_ca_certificate": tls.root_ca, "enable_mtls": True,
         "connect_certificate": tls.cert, "connect_private_key": tls.key,
         "verify_name_on_connect": bool(tls.verify_name)}
    if listen:  # a peer that accepts TLS links requires client certificates too
        d.update(listen_certificate=tls.cert, listen_private_key=tls.key)
    return d


MAX_MESSAGE_SIZE_KEY = "transport/link/rx/max_message_size"
# Redial a lost router after 0.1 s, doubling to at most 1 s between tries. Zenoh's
# default (1 s doubling to 4 s) leaves every service deaf for 1-4 s after a router
# restart, and fail-closed actors execute nothing meanwhile (tests/test_reconciliation.py).
CONNECT_RETRY = {"period_init_ms": 100, "period_max_ms": 1000, "period_increase_factor": 2}


def zenoh_config(*, connect: Sequence[str] = (), listen: Sequence[str] = (),
                 mode: str = "peer", multicast_scouting: bool = False,
                 tls: TlsFiles | None = None, max_message_bytes: int = 0) -> zenoh.Config:
    """Zenoh config with explicit endpoints only.

    Multicast scouting is off by default so a process never attaches to a
    stranger's network by accident; multi-host runs list a router in
    ``connect`` (docs/wire.md, deploy/). ``tls`` (see ``TlsFiles``) adds the
    TLS link settings; with it every endpoint must be a ``tls/`` one, so a
    typo can never silently fall back to plain TCP. ``max_message_bytes`` (> 0)
    is Zenoh's own limit on a message a link receives (Zenoh's default is
    1 GiB): a larger one is never reassembled, so it costs no memory here.
    A lost link to a ``connect`` endpoint is redialled soon (``CONNECT_RETRY``).
    """
    if mode not in ("peer", "client", "router"):
        raise ValueError(f"zenoh mode {mode!r}")
    if tls is not None and tls.enabled:
        plain = [e for e in (*connect, *listen) if not str(e).startswith("tls/")]
        if plain:
            raise ValueError(f"TLS is configured but endpoints {plain} are not tls/<host>:<port>")
    cfg = zenoh.Config()
    cfg.insert_json5("mode", json.dumps(mode))
    cfg.insert_json5("scouting/multicast/enabled", json.dumps(bool(multicast_scouting)))
    cfg.insert_json5("scouting/gossip/enabled", json.dumps(bool(multicast_scouting)))
    cfg.insert_json5("connect/endpoints", json.dumps(list(connect)))
    cfg.insert_json5("connect/retry", json.dumps(CONNECT_RETRY))
    cfg.insert_json5("listen/endpoints", json.dumps(list(listen)))
    if tls is not None and tls.enabled:
        cfg.insert_json5("transport/link/tls", json.dumps(tls_link_config(tls, listen=bool(listen))))
    if max_message_bytes > 0:
        cfg.insert_json5(MAX_MESSAGE_SIZE_KEY, json.dumps(int(max_message_bytes)))
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

    def __init__(self, session: zenoh.Session, declare_publishers: bool = True):
        self._session = session
        # Declared publishers are Zenoh's fast path; behind a router with access
        # control (TLS deployments) zenoh 1.10 delivers only the first put of a
        # declared publisher (measured: 1 of 10), so those sessions put directly.
        self._declare_publishers = declare_publishers
        self._publishers: dict[str, zenoh.Publisher] = {}
        self._entities: list = []
        self._lock = threading.Lock()
        self._closed = False

    @classmethod
    def open(cls, *, connect: Sequence[str] = (), listen: Sequence[str] = (),
             mode: str = "peer", inprocess: bool = False,
             tls: TlsFiles | None = None, role: str | None = None, max_message_bytes: int = 0,
             member: int | str | None = None) -> "Bus":
        """``tls``: this process's certificate files (``role`` fills a
        ``{role}`` placeholder in their paths); ignored in-process.
        ``max_message_bytes``: Zenoh's limit on a received message (0: Zenoh's)."""
        if inprocess:
            connect, listen, tls = (), (), None
        if tls is not None:
            tls = tls.for_role(role, member) if tls.enabled else None
        return cls(zenoh.open(zenoh_config(connect=connect, listen=listen, mode=mode, tls=tls,
                                           max_message_bytes=max_message_bytes)),
                   declare_publishers=tls is None)

    @classmethod
    def from_transport(cls, transport, *, role: str | None = None, mode: str | None = None,
                       inprocess: bool = False, max_message_bytes: int = 0,
                       member: int | str | None = None) -> "Bus":
        """``Bus.open`` from a ``services.config.TransportConfig`` (endpoints,
        mode and the ``tls_*`` fields); ``mode`` overrides the config's."""
        return cls.open(connect=list(transport.connect), listen=list(transport.listen),
                        mode=mode or transport.mode, inprocess=inprocess,
                        tls=TlsFiles.from_transport(transport), role=role, max_message_bytes=max_message_bytes,
                        member=member)

    # ------------------------------------------------------------- pub/sub
    def publish(self, key: str, payload: bytes) -> None:
        with self._lock:
            if self._closed:
                return
            if not self._declare_publishers:
                self._session.put(key, payload)
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
    def serve(self, key: str, maxsize: int = 0,
              on_full: Callable[[], None] | None = None) -> "queue.Queue[Request]":
        """Declare a queryable; received queries land in the returned queue. With
        ``maxsize`` the queue is bounded: a query that finds it full is answered at
        once with ``reply_err(b"overloaded: ...")`` and ``on_full()`` counts it."""
        q: queue.Queue[Request] = queue.Queue(maxsize=maxsize)

        def _cb(query: zenoh.Query) -> None:
            payload = query.payload.to_bytes() if query.payload is not None else b""
            req = Request(query, payload, time.perf_counter())
            try:
                q.put_nowait(req)
            except queue.Full:
                req.reply_err(b"overloaded: queue full, retry")
                if on_full is not None:
                    on_full()

        with self._lock:
            self._entities.append(self._session.declare_queryable(key, _cb))
        return q

    def request(self, key: str, payload: bytes, timeout: float) -> Reply | None:
        """One get; the first reply, or None when nobody answered in time."""
        return next(self.replies(key, payload, timeout), None)

    def replies(self, key: str, payload: bytes, timeout: float) -> Iterator[Reply]:
        """One get sent to every queryable on ``key``, every reply as it arrives,
        so a caller that checks answers takes the first that passes. Zenoh's
        defaults (best-matching target, replies consolidated by key) would let one
        bad queryable answering on the same key hide the good one's answer.
        Ends when the query is finalized or times out.

        The get is sent when this is called, not when iteration starts:
        replies queue up in Zenoh's channel meanwhile, so a caller can send
        several queries and then collect them (the pipelined actor). A closed
        bus sends nothing and has no replies (as ``publish`` sends nothing)."""
        if self._closed:
            return iter(())
        try:
            handler = self._session.get(key, payload=payload, timeout=float(timeout), target=zenoh.QueryTarget.ALL,
                                        consolidation=zenoh.ConsolidationMode.NONE)
        except zenoh.ZError:
            if self._closed:   # closed by another thread meanwhile
                return iter(())
            raise
        return (Reply(ok=r.ok.payload.to_bytes()) if r.ok is not None else Reply(err=r.err.payload.to_bytes())
                for r in handler)

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
