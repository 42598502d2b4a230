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

# A service's exit code for a fault restarting cannot fix (every checkpoint of the
# run directory damaged): the supervisor stops the run with it instead of restarting
EXIT_FATAL = 4


# a learner budget of this many updates or more is "no update budget" (a --minutes run)
UNBOUNDED_UPDATES = 10**8


def budget_part(learner: dict, eta_s: float | None = None) -> str | None:
    """``update 37/100 (37%), ETA 1m05s`` from the learner's heartbeat (``updates``,
    extra ``budget_updates`` and ``progress``, the share of the budget spent, updates
    or minutes); None without a learner heard from."""
    if not learner:
        return None
    extra = learner.get("extra", {})
    n, budget, prog = int(learner.get("updates", 0)), extra.get("budget_updates"), extra.get("progress")
    if prog is not None and prog >= 1.0:
        eta_s = 0.0   # the budget is spent
    text = f"update {n}/{int(budget)}" if budget and budget < UNBOUNDED_UPDATES else f"update {n}"
    if prog is not None:
        text += f" ({100 * prog:.0f}%)"
    return text + f", ETA {format_duration(eta_s)}"


def status_line(fresh: dict[str, dict], latest: dict[str, dict] | None = None, eta_s: float | None = None) -> str:
    """One line from the heartbeats: the learner's updates out of its budget with the
    ETA ``eta_s`` (``StatusBoard.eta``), env steps/s (sum over actors heard from
    recently, ``fresh``), parameter version (learner), recent success rate
    (learner, else the actors' mean), the learner's last deterministic
    deployment probe (if any), shield p99 solve latency (slowest shard), unhealthy
    members. Version, success rate and p99 come from ``latest`` (default
    ``fresh``): a learner busy in a long update keeps its last values."""
    latest = fresh if latest is None else latest
    actors = [b for k, b in fresh.items() if k.startswith("actor/")]
    learner = latest.get("learner/0", {})
    shield_p99 = [b["shield_p99_s"] for k, b in latest.items()
                  if k.startswith("shield/") and b.get("shield_p99_s") is not None]
    sps = sum(b["env_steps_per_s"] for b in actors)
    sr = learner.get("success_rate")
    if sr is None:
        srs = [b["success_rate"] for b in actors if b.get("success_rate") is not None]
        sr = sum(srs) / len(srs) if srs else None
    p99 = max(shield_p99) if shield_p99 else None   # the slowest shard
    deploy_sr = learner.get("extra", {}).get("deploy_sr")   # the learner's deterministic probe
    budget = budget_part(learner, eta_s)
    parts = ([budget] if budget else []) + [
        f"steps/s {sps:8.1f}", f"version {learner.get('version', -1)}", f"SR {sr:.2f}" if sr is not None else "SR -"]
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

    def __init__(self, run_id: str, stale_after_s: float = 5.0, clock=time.monotonic):
        self.run_id = run_id
        self.stale_after_s = stale_after_s
        self.clock = clock               # monotonic seconds (a fake one in tests)
        self._progress0: tuple | None = None   # (learner pid, time, progress) first heard: the ETA's start
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
        body = dict(msg.body, received=self.clock())
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
        now = self.clock()
        with self._lock:
            return {k: b for k, b in self.latest.items() if now - b["received"] <= self.stale_after_s}

    def members(self) -> dict[str, dict]:
        """Latest body per member, without the receive stamp."""
        with self._lock:
            return {k: {f: v for f, v in b.items() if f != "received"} for k, b in self.latest.items()}

    def snapshot(self) -> dict:
        return {"members": self.members(), "rejected": self.rejected, "line": self.line()}

    def eta(self) -> float | None:
        """Seconds until the learner's budget is spent, at the rate its progress moved
        since this board first heard the current learner process (a restarted learner
        starts the measurement again); None before it has moved."""
        with self._lock:
            learner = self.latest.get("learner/0")
        prog = (learner or {}).get("extra", {}).get("progress")
        if prog is None:
            return None
        now = self.clock()
        if self._progress0 is None or self._progress0[0] != learner.get("pid"):
            self._progress0 = (learner.get("pid"), now, prog)
        _, t0, p0 = self._progress0
        if prog >= 1.0:
            return 0.0
        if prog <= p0 or now <= t0:
            return None
        return (now - t0) / (prog - p0) * (1.0 - prog)

    def line(self, own: dict[str, dict] | None = None) -> str:
        """The status line; ``own``: members' bodies known first-hand (an in-process
        run's final line takes the learner's own final state, not a heartbeat that may
        still be on its way)."""
        eta = self.eta()
        with self._lock:
            latest = dict(self.latest)
        fresh = self.fresh()
        for k, body in (own or {}).items():
            latest[k] = fresh[k] = {**latest.get(k, {}), **body}
        return status_line(fresh, latest, eta)

    def close(self) -> None:
        if self._own_bus and self._bus is not None:
            self._bus.close()
        self._bus = None


def is_tty(out) -> bool:
    try:
        return bool(out.isatty())
    except (AttributeError, ValueError):   # no isatty, or a closed stream
        return False


class LiveLine:
    """Shows a status line: rewritten in place on a terminal (every call),
    else one plain line every ``log_period_s`` (a log file gets whole lines).
    ``clock``: seconds, monotonic (a fake one in tests)."""

    def __init__(self, out, log_period_s: float = 10.0, clock=time.monotonic):
        self.out = out
        self.tty = is_tty(out)
        self.log_period_s = log_period_s
        self.clock = clock
        self._last_log = -float("inf")

    def show(self, line: str) -> None:
        if self.tty:
            self.out.write("\r" + line + "   ")
            self.out.flush()
        elif self.clock() - self._last_log >= self.log_period_s:
            self._last_log = self.clock()
            print(line, file=self.out, flush=True)

    def close(self, line: str | None = None) -> None:
        """End the live line (a final ``line`` is always printed whole)."""
        if line is not None:
            self.out.write(("\r" if self.tty else "") + line + "\n")
            self.out.flush()
        elif self.tty:
            self.out.write("\n")


def format_duration(seconds: float | None) -> str:
    """``45s``, ``3m05s``, ``2h04m``; ``-`` for unknown."""
    if seconds is None or not seconds == seconds or seconds == float("inf"):
        return "-"
    s = max(0, int(round(seconds)))
    if s < 60:
        return f"{s}s"
    if s < 3600:
        return f"{s // 60}m{s % 60:02d}s"
    return f"{s // 3600}h{s % 3600 // 60:02d}m"


class Progress:
    """Progress of a fixed amount of work (the runs of a suite, the episodes of an
    evaluation), as one line::

        suite [########------------] 4/10 runs, 2 running, 1 failed | 6m12s elapsed, ETA 9m30s

    On a terminal the line is a bar rewritten in place (on every change of the
    counts, else at most every ``tty_period_s``); anywhere else (a log file, a
    pipe) it is one plain line every ``log_period_s``, the first after one period,
    so a short job prints none. ``clear`` wipes the bar before other output on the
    terminal; ``close`` ends it (elsewhere: prints the final state if any line was
    printed). The ETA is the caller's (``eta_s``) or, without one, the mean time
    per finished item times the items left. ``clock``: monotonic seconds (tests
    pass a fake one)."""

    def __init__(self, out, total: int, label: str, unit: str = "", log_period_s: float = 10.0,
                 tty_period_s: float = 0.2, width: int = 20, clock=time.monotonic):
        self.out, self.total, self.label, self.unit = out, max(0, int(total)), label, unit
        self.tty = is_tty(out)
        self.log_period_s, self.tty_period_s, self.width, self.clock = log_period_s, tty_period_s, width, clock
        self.t0 = clock()
        self.done, self.running, self.failed, self.eta_s, self.note = 0, None, 0, None, ""
        self._last_write = self.t0 if not self.tty else -float("inf")
        self._shown = 0            # length of the bar on the terminal (0: none shown)
        self._printed = False      # a plain line was printed (not a terminal)
        self._state = None

    def eta(self) -> float | None:
        if self.total and self.done + self.failed >= self.total:
            return 0.0
        if self.eta_s is not None:
            return self.eta_s
        if self.done <= 0:
            return None
        left = max(self.total - self.done - self.failed, 0)
        return (self.clock() - self.t0) / self.done * left

    def line(self) -> str:
        ended = min(self.done + self.failed, self.total)
        frac = ended / self.total if self.total else 1.0
        unit = f" {self.unit}" if self.unit else ""
        parts = [f"{self.done}/{self.total}{unit}"]
        if self.running is not None:
            parts.append(f"{self.running} running")
        if self.failed:
            parts.append(f"{self.failed} failed")
        text = ", ".join(parts) + (f" | {self.note}" if self.note else "")
        text += f" | {format_duration(self.clock() - self.t0)} elapsed, ETA {format_duration(self.eta())}"
        if self.tty:
            filled = int(round(frac * self.width))
            return f"{self.label} [{'#' * filled}{'-' * (self.width - filled)}] {text}"
        return f"{self.label}: {100 * frac:3.0f}% {text}"

    def update(self, done: int, running: int | None = None, failed: int = 0, eta_s: float | None = None,
               note: str = "") -> None:
        self.done, self.running, self.failed, self.eta_s, self.note = done, running, failed, eta_s, note
        now = self.clock()
        if self.tty:
            state = (done, running, failed)
            if state != self._state or not self._shown or now - self._last_write >= self.tty_period_s:
                self._state = state
                self._draw(now)
        elif now - self._last_write >= self.log_period_s:
            self._last_write = now
            self._printed = True
            print(self.line(), file=self.out, flush=True)

    def _draw(self, now: float) -> None:
        line = self.line()
        self.out.write("\r" + line + " " * max(self._shown - len(line), 0))
        self.out.flush()
        self._shown, self._last_write = len(line), now

    def clear(self) -> None:
        """Wipe the bar off the terminal line (it is redrawn on the next update)."""
        if self.tty and self._shown:
            self.out.write("\r" + " " * self._shown + "\r")
            self.out.flush()
            self._shown = 0

    def close(self) -> None:
        if self.tty:
            self._draw(self.clock())
            self.out.write("\n")
            self.out.flush()
            self._shown = 0
        elif self._printed:
            print(self.line(), file=self.out, flush=True)
