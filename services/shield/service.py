"""Shield service: one Zenoh queryable (shard ``k`` of ``shields``, key
``sage/<run>/shield/<k>``, asked by actors ``i % shields == k``) that
micro-batches its actors' CBF-QP requests into one ``solve_cbf_qp`` call
(Eq. qpshield) and replies per request.

Batching rule: after the first waiting request arrives, keep collecting for
at most ``shield.window_s`` or until ``shield.max_batch`` QP rows are queued,
then solve everything in one call (requests of different row counts M are
padded to the largest with masked-out zero rows). Every query is finished (dropped) exactly
once, with a reply or a ``reply_err`` carrying ``"<reason>: <detail>"``.
"""
from __future__ import annotations

import queue
import time

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

    def status_fields(self) -> dict:
        return {"shield_p99_s": self.solve_window.quantile(0.99),
                "extra": {"requests": float(self.n_requests), "rows": float(self.n_rows),
                          "dropped": float(self.n_dropped),
                          "rows_per_s": self.rows_rate.rate(), "busy_s_total": self.busy_s,
                          "queue_depth": float(self._queue.qsize() if self._queue else 0)}}

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
            try:
                first = q.get(timeout=0.05)
            except queue.Empty:
                continue
            batch = [first]
            good: list[tuple[Request, dict]] = []
            rows = self._admit(first, good)
            deadline = time.perf_counter() + self.cfg.shield.window_s
            # A synchronous actor has at most one request waiting, so once one
            # per actor of this shard is queued nobody else is coming: close the
            # window early (a pipelined actor's second group rides in the next batch).
            expected = max(1, self.cfg.actors_of_shard(self.member_id))
            while rows < self.cfg.shield.max_batch and len(batch) < expected:
                remaining = deadline - time.perf_counter()
                try:
                    req = q.get_nowait() if remaining <= 0 else q.get(timeout=remaining)
                except queue.Empty:
                    break
                batch.append(req)
                rows += self._admit(req, good)
            self.m.shield_queue.labels(**self.labels).set(q.qsize())
            self.handle(batch, good)
        self.state = "stopped"
        self.publish_status(force=True)
        # answer what is left so no asker waits for its timeout
        while True:
            try:
                q.get_nowait().reply_err(b"stopping: shield shutting down")
            except queue.Empty:
                break
        return 0

    def _on_full(self) -> None:
        self.n_dropped += 1
        self.m.dropped.labels(**self.labels, queue="shield_queries").inc()

    def _admit(self, req: Request, good: list) -> int:
        """Decode one request into ``good``; a bad one is answered with
        reply_err at once. Returns its number of QP rows."""
        t0 = time.perf_counter()
        try:
            return self._decode_request(req, good)
        finally:
            self.busy_s += time.perf_counter() - t0

    def _decode_request(self, req: Request, good: list) -> int:
        self.n_requests += 1
        self.m.shield_requests.labels(**self.labels).inc()
        msg = self.decode(req.payload, "shield_req")
        if msg is None:
            self._error(req, "rejected", "request failed wire validation")
            return 0
        good.append((req, msg.body))
        return msg.body["a_prop"].shape[0]

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
