"""The one-line live status of a run, from the services' heartbeats
(``sage/<run>/status/**``, schema in docs/wire.md): ``StatusBoard`` collects
them, ``status_line`` formats them. Shared by the thread launcher and the
process supervisor, so both show the same figures."""
from __future__ import annotations

import threading
import time
from collections.abc import Sequence

from common import keys, wire
from common.transport import Bus, TlsFiles


def status_line(fresh: dict[str, dict], latest: dict[str, dict] | None = None) -> str:
    """One line from the heartbeats: env steps/s (sum over actors heard from
    recently, ``fresh``), parameter version (learner), recent success rate
    (learner, else the actors' mean), the learner's last deterministic
    deployment probe (if any), shield p99 solve latency, unhealthy
    members. Version, success rate and p99 come from ``latest`` (default
    ``fresh``): a learner busy in a long update keeps its last values."""
    latest = fresh if latest is None else latest
    actors = [b for k, b in fresh.items() if k.startswith("actor/")]
    learner = latest.get("learner/0", {})
    shield = latest.get("shield/0", {})
    sps = sum(b["env_steps_per_s"] for b in actors)
    sr = learner.get("success_rate")
    if sr is None:
        srs = [b["success_rate"] for b in actors if b.get("success_rate") is not None]
        sr = sum(srs) / len(srs) if srs else None
    p99 = shield.get("shield_p99_s")
    deploy_sr = learner.get("extra", {}).get("deploy_sr")   # the learner's deterministic probe
    parts = [f"steps/s {sps:8.1f}", f"version {learner.get('version', -1)}",
             f"SR {sr:.2f}" if sr is not None else "SR -"]
    if deploy_sr is not None:
        parts.append(f"deploy SR {deploy_sr:.2f}")
    parts += [f"shield p99 {p99 * 1e3:.2f} ms" if p99 is not None else "shield p99 -",
              f"actors {len(actors)}"]
    bad = sorted(k for k, b in fresh.items() if b.get("state") == "unhealthy")
    if bad:
        parts.append("UNHEALTHY " + ",".join(bad))
    return " | ".join(parts)


class StatusBoard:
    """Latest ``status`` body of every service of one run, fed by a Zenoh
    subscription on ``sage/<run>/status/**``: on a bus it is given (``attach``,
    in-process) or on its own client session (``subscribe``, supervisor)."""

    def __init__(self, run_id: str, stale_after_s: float = 5.0):
        self.run_id = run_id
        self.stale_after_s = stale_after_s
        self.latest: dict[str, dict] = {}
        self.rejected = 0
        self._lock = threading.Lock()
        self._bus: Bus | None = None
        self._own_bus = False

    def on_message(self, _key: str, payload: bytes) -> None:
        try:
            msg = wire.decode(payload, run_id=self.run_id, expect="status")
        except wire.WireError:
            self.rejected += 1  # shown in status.json; a bad heartbeat never stops a run
            return
        body = dict(msg.body, received=time.monotonic())
        with self._lock:
            self.latest[f"{body['role']}/{body['id']}"] = body

    def attach(self, bus: Bus) -> "StatusBoard":
        self._bus = bus
        bus.subscribe(keys.status_all(self.run_id), self.on_message)
        return self

    def subscribe(self, connect: Sequence[str], mode: str = "client", tls: TlsFiles | None = None) -> "StatusBoard":
        """Its own session to the router; with ``tls``, as the ``supervisor`` role."""
        self._own_bus = True
        return self.attach(Bus.open(connect=list(connect), mode=mode, tls=tls, role="supervisor"))

    def stop_run(self) -> None:
        """Publish a ``control`` stop to every service of the run (also remote ones)."""
        if self._bus is not None:
            self._bus.publish(keys.control(self.run_id), wire.encode(
                "control", {"command": "stop", "target": "*"}, run_id=self.run_id, sender="supervisor/0", seq=0))

    def fresh(self) -> dict[str, dict]:
        now = time.monotonic()
        with self._lock:
            return {k: b for k, b in self.latest.items() if now - b["received"] <= self.stale_after_s}

    def members(self) -> dict[str, dict]:
        """Latest body per member, without the receive stamp."""
        with self._lock:
            return {k: {f: v for f, v in b.items() if f != "received"} for k, b in self.latest.items()}

    def snapshot(self) -> dict:
        return {"members": self.members(), "rejected": self.rejected, "line": self.line()}

    def line(self) -> str:
        with self._lock:
            latest = dict(self.latest)
        return status_line(self.fresh(), latest)

    def close(self) -> None:
        if self._own_bus and self._bus is not None:
            self._bus.close()
        self._bus = None


class LiveLine:
    """Shows a status line: rewritten in place on a terminal (every call),
    else one plain line every ``log_period_s`` (a log file gets whole lines)."""

    def __init__(self, out, log_period_s: float = 10.0):
        self.out = out
        self.tty = hasattr(out, "isatty") and out.isatty()
        self.log_period_s = log_period_s
        self._last_log = -float("inf")

    def show(self, line: str) -> None:
        if self.tty:
            self.out.write("\r" + line + "   ")
            self.out.flush()
        elif time.monotonic() - self._last_log >= self.log_period_s:
            self._last_log = time.monotonic()
            print(line, file=self.out, flush=True)

    def close(self, line: str | None = None) -> None:
        """End the live line (a final ``line`` is always printed whole)."""
        if line is not None:
            self.out.write(("\r" if self.tty else "") + line + "\n")
            self.out.flush()
        elif self.tty:
            self.out.write("\n")
