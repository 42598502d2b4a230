"""Shield service: one Zenoh queryable (shard ``k`` of ``shields``, key
``sage/<run>/shield/<k>``, asked by actors ``i % shields == k``) that
micro-batches its actors' CBF-QP requests into one ``solve_cbf_qp`` call
(Eq. qpshield) and replies per request.

Batching rule: after the first waiting request arrives, keep collecting for
at most ``shield.window_s`` or until ``shield.max_batch`` QP rows are queued,
then solve everything in one call (requests of different row counts M are
padded to the largest with masked-out zero rows). Every query is finished (dropped) exactly
once, with a reply or a ``reply_err`` carrying ``"<reason>: <detail>"``.

Budgets (issue 32: one request must not stall the shield): a request's size
is capped at decode by the run's spec, ``M <= env.max_rows`` rows per problem
and ``B <= max(envs_per_actor, shield.max_batch)`` problems (a ``limit``
rejection, counted), so one solve's cost is bounded by ``max_batch`` problems
of at most ``max_rows`` rows, each under the QP's own iteration cap
(``QPConfig.max_iter``; an uncertified answer is STATUS_MAX_ITER, which actors
refuse). A request that waited longer than the actors' ``shield_timeout_s``
is not solved (its asker gave up; answered ``expired``, counted). Service is
fair across senders: decoded requests wait in one bounded FIFO per sender
(``shield.max_pending_per_sender``, and ``shield.max_queue`` in all; overflow
answered ``overloaded`` and counted) and each batch takes them round-robin, so a flooding sender gets its
share of the solver and no more.
"""
from __future__ import annotations

import queue
import time
from collections import OrderedDict, deque

import numpy as np

from common import keys
from common.metrics_prom import Window
from common.safety_rows import SafetyRows
from common.shield.qp import shield_actions
from common.spec import JOINT_ACT_DIM
from common.transport import Request
from services.base import RateMeter, Service


def _default_solver(backend: str):
    def solve(a_prop, rows: SafetyRows):
        return shield_actions(a_prop, rows, backend=backend)

    return solve


class ShieldService(Service):
    role = "shield"

    def __init__(self, cfg, bus, member_id=0, registry=None, stop=None, solve=None):
        super().__init__(cfg, bus, member_id, registry, stop)
        self.solve = solve if solve is not None else _default_solver(cfg.shield.backend)
        self.solve_window = Window()
        self.n_requests = 0
        self.n_rows = 0
        self.n_dropped = 0   # queries answered "overloaded" because the queue was full
        self.rows_rate = RateMeter()
        self.busy_s = 0.0   # decoding, solving and replying (not waiting): capacity = rows / busy_s
        self._queue: queue.Queue[Request] | None = None
        # decoded requests waiting for a batch, one FIFO per sender (round-robin service)
        self._pending: OrderedDict[str, deque[tuple[Request, dict]]] = OrderedDict()
        self._pending_rows = 0
        self._n_pending = 0   # queries in all FIFOs together, at most shield.max_queue
        self.n_expired = 0    # requests older than the actors' timeout, not solved
        self.n_unfair = 0     # requests refused because their sender already had its share waiting
        # the run's spec caps one request (wire "limit" beyond): rows per problem, problems
        self.bounds = {"M": int(cfg.env.max_rows), "B": max(int(cfg.envs_per_actor), int(cfg.shield.max_batch))}

    def status_fields(self) -> dict:
        return {"shield_p99_s": self.solve_window.quantile(0.99),
                "extra": {"requests": float(self.n_requests), "rows": float(self.n_rows),
                          "dropped": float(self.n_dropped), "expired": float(self.n_expired),
                          "sender_overflow": float(self.n_unfair),
                          "rows_per_s": self.rows_rate.rate(), "busy_s_total": self.busy_s,
                          "queue_depth": float(self._queue.qsize() if self._queue else 0),
                          "waiting": float(self._n_pending)}}

    # ------------------------------------------------------------- loop
    def warm_up(self) -> None:
        """One tiny solve before serving, so a JIT-compiled backend does not
        time out the first real query (numba compiles on first call)."""
        try:
            self.solve(np.zeros((1, JOINT_ACT_DIM)), SafetyRows(np.zeros((1, 1, JOINT_ACT_DIM)), np.zeros((1, 1)),
                                                                np.ones((1, 1), bool), np.zeros((1, JOINT_ACT_DIM), bool)))
        except Exception as exc:  # noqa: BLE001 - a broken solver is reported per query later
            self.log.warning("warm-up solve failed: %s", exc)

    def run(self) -> int:
        self.warm_up()
        self._queue = q = self.bus.serve(keys.shield(self.cfg.run_id, self.member_id), maxsize=self.cfg.shield.max_queue,
                                         on_full=self._on_full)
        self.listen_control()
        self.state = "running"
        self.publish_status(force=True)
        while not self.stop.is_set():
            self.publish_status()
            self._drain(q, wait=0.0 if self._pending else 0.05)
            if not self._pending:
                continue
            deadline = time.perf_counter() + self.cfg.shield.window_s
            # A synchronous actor has at most one request waiting, so once one
            # per actor of this shard is queued nobody else is coming: close the
            # window early (a pipelined actor's second group rides in the next batch).
            expected = max(1, self.cfg.actors_of_shard(self.member_id))
            while self._pending_rows < self.cfg.shield.max_batch and len(self._pending) < expected:
                remaining = deadline - time.perf_counter()
                if remaining <= 0 or not self._drain(q, wait=remaining, most=1):
                    break
            self.m.shield_queue.labels(**self.labels).set(q.qsize())
            good = self._fair_batch()
            self.handle([req for req, _ in good], good)
        self.state = "stopped"
        self.publish_status(force=True)
        # answer what is left so no asker waits for its timeout
        for waiting in self._pending.values():
            for req, _ in waiting:
                req.reply_err(b"stopping: shield shutting down")
        self._pending.clear()
        self._n_pending = self._pending_rows = 0
        while True:
            try:
                q.get_nowait().reply_err(b"stopping: shield shutting down")
            except queue.Empty:
                break
        return 0

    def _on_full(self) -> None:
        self.n_dropped += 1
        self.m.dropped.labels(**self.labels, queue="shield_queries").inc()

    def _drain(self, q: queue.Queue, wait: float, most: int | None = None) -> int:
        """Move received queries into their senders' FIFOs (decoded and checked):
        block up to ``wait`` s for the first, then take what is there, at most
        ``most``. Returns how many were taken."""
        n = 0
        while most is None or n < most:
            try:
                req = q.get(timeout=wait) if n == 0 and wait > 0 else q.get_nowait()
            except queue.Empty:
                break
            n += 1
            self._admit(req)
        return n

    def _admit(self, req: Request) -> None:
        """Decode one request into its sender's FIFO; a bad, expired or
        over-share one is answered with reply_err at once."""
        t0 = time.perf_counter()
        try:
            self._decode_request(req)
        finally:
            self.busy_s += time.perf_counter() - t0

    def _decode_request(self, req: Request) -> None:
        self.n_requests += 1
        self.m.shield_requests.labels(**self.labels).inc()
        msg = self.decode(req.payload, "shield_req", bounds=self.bounds)
        req.payload = b""   # the bytes are decoded (or refused): do not hold them while waiting
        if msg is None:
            self._error(req, "rejected", "request failed wire validation")
            return
        waiting = self._pending.get(msg.sender, ())
        if len(waiting) >= self.cfg.shield.max_pending_per_sender or self._n_pending >= self.cfg.shield.max_queue:
            # one sender's share, or all of them (a flood under ever new sender names)
            self.n_unfair += 1
            self.m.dropped.labels(**self.labels, queue="shield_sender").inc()
            self._error(req, "overloaded", f"{msg.sender} has {len(waiting)} of {self._n_pending} queries waiting, retry")
            return
        self._pending.setdefault(msg.sender, deque()).append((req, msg.body))
        self._pending_rows += msg.body["a_prop"].shape[0]
        self._n_pending += 1

    def _fair_batch(self) -> list[tuple[Request, dict]]:
        """Up to ``shield.max_batch`` rows of waiting requests, taken round-robin
        over senders (one request per sender per round, the oldest first), and
        never one that waited past the actors' timeout (answered ``expired``)."""
        good: list[tuple[Request, dict]] = []
        rows, max_rows = 0, self.cfg.shield.max_batch
        expire_s = self.cfg.actor.shield_timeout_s
        now = time.perf_counter()
        while self._pending and rows < max_rows:
            sender, waiting = next(iter(self._pending.items()))
            req, body = waiting[0]
            n = body["a_prop"].shape[0]
            if good and rows + n > max_rows:
                break
            waiting.popleft()
            self._pending_rows -= n
            self._n_pending -= 1
            if waiting:
                self._pending.move_to_end(sender)   # its next request waits for the others' turn
            else:
                del self._pending[sender]
            if now - req.t_recv > expire_s:
                self.n_expired += 1
                self._error(req, "expired", f"waited {now - req.t_recv:.3f} s, past the actors' timeout")
                continue
            good.append((req, body))
            rows += n
        return good

    def handle(self, batch: list[Request], good: list[tuple[Request, dict]]) -> None:
        """Solve all admitted requests in one call, their rows padded to the
        largest M (requests of pruned rows differ in M), and reply per request;
        finishes every request of the batch, whatever happens."""
        t0 = time.perf_counter()
        try:
            if good and not self._solve_group(good, isolate=len(good) > 1):
                # the joint solve failed: solve each request alone, so one bad
                # request cannot take the others' answers with it
                for item in good:
                    self._solve_group([item])
        finally:
            for req in batch:
                req.finish()  # idempotent; no query is ever left open
            self.busy_s += time.perf_counter() - t0

    def _solve_group(self, items: list[tuple[Request, dict]], isolate: bool = False) -> bool:
        """One solve for ``items`` (rows padded to their largest M) and the replies.
        On a solver failure: with ``isolate`` return False without replying (the
        caller retries request by request), else reply the error to every asker."""
        a_prop = np.concatenate([b["a_prop"] for _, b in items])
        rows = SafetyRows.concat([SafetyRows.of(b) for _, b in items], pad=True)
        B = a_prop.shape[0]
        t0 = time.perf_counter()
        try:
            res = self.solve(a_prop, rows)
            a_exec = np.asarray(res.a_exec, dtype=np.float64)
            if a_exec.shape != a_prop.shape or not np.isfinite(a_exec).all():
                raise ValueError(f"solver returned a_exec {a_exec.shape}, finite={np.isfinite(a_exec).all()}")
        except Exception as exc:  # noqa: BLE001 - reported to every asker, loop goes on
            if isolate:
                self.log.warning("joint solve of %d rows (%d requests) failed, solving them one by one: %s",
                                 B, len(items), exc)
                return False
            reason = "invalid_input" if isinstance(exc, ValueError) else "solver_error"
            self.log.warning("solve of %d rows failed: %s", B, exc)
            for req, _ in items:
                self._error(req, reason, str(exc))
            return True
        dt = time.perf_counter() - t0
        status = np.asarray(res.status, dtype=np.int32)
        corr = np.asarray(res.correction_norm, dtype=np.float64)
        slack = np.asarray(res.slack, dtype=np.float64)
        self.solve_window.add(dt)
        self.n_rows += B
        self.rows_rate.add(self.n_rows)
        lab = self.labels
        self.m.shield_solve.labels(**lab).observe(dt)
        self.m.shield_batch.labels(**lab).observe(B)
        self.m.shield_infeasible.labels(**lab).inc(int((status == 1).sum()))
        h = self.m.shield_correction.labels(**lab)
        for x in corr:
            h.observe(float(x))
        start = 0
        for req, body in items:
            n = body["a_prop"].shape[0]
            sl = slice(start, start + n)
            start += n
            try:
                req.reply(self.encode("shield_rep", {
                    "a_exec": a_exec[sl], "status": status[sl], "correction_norm": corr[sl],
                    "slack": slack[sl], "batch_size": B, "solve_s": dt}))
            except Exception as exc:  # noqa: BLE001 - e.g. asker gone
                self.log.warning("reply failed: %s", exc)
        return True

    def _error(self, req: Request, reason: str, detail: str) -> None:
        self.m.shield_errors.labels(**self.labels, reason=reason).inc()
        try:
            req.reply_err(f"{reason}: {detail}".encode())
        except Exception as exc:  # noqa: BLE001
            self.log.warning("reply_err failed: %s", exc)
