"""Steady-state rates from the services' status heartbeats (``StepMeter``),
latency quantiles, and a thread that repeats a call (the bench's parameter
feeder)."""
from __future__ import annotations

import threading
import time

import numpy as np

from common import wire


def quantiles_ms(samples_s) -> dict:
    x = np.asarray(samples_s, dtype=float) * 1e3
    return {"p50": float(np.quantile(x, 0.5)), "p99": float(np.quantile(x, 0.99)), "n": int(x.size)}


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



class Repeater:
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
