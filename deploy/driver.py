"""The one run driver of SAGE's process placements: what every placement does
the same way, whatever runs its members (local process groups,
``deploy/supervisor.py``; Ray actors, ``deploy/ray_run.py``).

The driver owns the run's records and its life cycle:

* ``supervisor.jsonl``: one JSON row per event (``event``); the first is
  ``supervisor_start``, the last ``supervisor_exit`` with the exit code;
* ``status.json``: the members' states and the services' heartbeats, refreshed
  every ``status_period_s`` and once more at the end (``write_status``);
* the live status line (``common.status.LiveLine``) and the one final line;
* the outcome: the first reason the run ended wins (``finish``); a member marked
  ``ends_run`` that exits 0 ends it normally, all members of wave 0 done too;
* signals: SIGINT/SIGTERM end the run with exit code 128 + signal, and a
  second signal skips the shutdown's wait (``signals``);
* the shutdown, wave by wave (lower ``stop_wave`` first, the router last).

A placement says only *where* and *how* a member runs: it subclasses
``RunDriver`` and implements ``start`` (launch every member), ``poll_members``
(reap exits, restart within its budget, ``finish`` on give-up) and
``stop_wave`` (stop one wave's members), plus the few words it adds to the
records (``start_fields``, ``member_status``, ``summary``'s extras). A new
placement (Kubernetes, Slurm) is one such class.
"""
from __future__ import annotations

import json
import os
import signal
import socket
import sys
import threading
import time
from dataclasses import asdict
from pathlib import Path
from typing import Callable, Protocol, Sequence

from common.rundir import RunDir, atomic_write_text
from common.status import LiveLine

EXIT_GAVE_UP = 1


def wait_tcp_ready(host: str, port: int, timeout_s: float, give_up: Callable[[], bool] = lambda: False) -> bool:
    """Until ``host:port`` accepts a TCP connection (True), ``timeout_s`` passes
    or ``give_up()`` is true (False); ``give_up`` may also raise."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline and not give_up():
        try:
            with socket.create_connection((host, port), timeout=0.5):
                return True
        except OSError:
            time.sleep(0.05)
    return False


def free_tcp_port(host: str = "127.0.0.1") -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind((host, 0))
        return s.getsockname()[1]


def kill_group(pid: int, sig: int) -> None:
    """``sig`` to the process group a member leads (started with its own session: pgid == pid)."""
    try:
        os.killpg(pid, sig)
    except (ProcessLookupError, PermissionError):
        pass


def parent_death_argv(argv: Sequence[str], python: str | None = None) -> list[str]:
    """``argv`` behind ``deploy.pdeathsig`` (run by ``python``, default ``argv[0]``): the
    process gets SIGTERM when this one (the supervisor, a Ray worker) dies. Linux only."""
    if not sys.platform.startswith("linux"):
        return list(argv)
    return [python or argv[0], "-m", "deploy.pdeathsig", str(os.getpid()), "--", *argv]


class StatusSource(Protocol):
    def line(self) -> str: ...
    def snapshot(self) -> dict: ...
    def close(self) -> None: ...


class Member:
    """The driver's view of one placed service (a placement adds its own fields)."""

    def __init__(self, spec):
        self.spec = spec               # a ``ServiceSpec``: name, argv, ends_run, stop_wave, ready_tcp
        self.state = "pending"
        self.starts = 0
        self.last_code: int | None = None

    @property
    def pid(self) -> int | None:
        return None


class RunDriver:
    """Runs ``members`` through a placement (the subclass) until the run ends; see
    the module docstring. ``run()`` is the blocking loop with signal handling;
    ``start()``, ``poll()`` and ``shutdown()`` are its steps, usable on their own."""

    label = "supervisor"               # the final line's and the records' name for the placement
    label_error: str | None = None     # the outcome's words when the driver itself fails (default: label)
    down_word, down_states = "down", ("backoff", "failed")   # the live line's members not up
    member_word = "procs"              # the live line's word for the members

    def __init__(self, members: Sequence[Member], run_dir: str | Path, cfg, *, out=None):
        names = [m.spec.name for m in members]
        if len(set(names)) != len(names):
            raise ValueError(f"duplicate service names in {names}")
        self.members = list(members)
        self.cfg = cfg                 # a dataclass with poll_s, status_period_s, status_log_period_s
        self.run_dir = Path(run_dir)
        self.paths = RunDir(run_dir)
        self.paths.logs.mkdir(parents=True, exist_ok=True)
        self.out = out if out is not None else sys.stderr
        self.outcome: tuple[int, str] | None = None
        self.signals: list[int] = []
        self._events_lock = threading.Lock()

    # ------------------------------------------------------------- the placement's part
    def start(self) -> None:
        raise NotImplementedError

    def poll_members(self) -> None:
        """Reap exits and answers, restart within the budget; ``finish`` when the run is over."""
        raise NotImplementedError

    def stop_wave(self, group: list[Member]) -> None:
        """Stop these members (SIGTERM, then SIGKILL after the deadline or a second signal)."""
        raise NotImplementedError

    def start_fields(self) -> dict:
        return {"pid": os.getpid()}

    def member_status(self, m: Member) -> dict:
        return {"state": m.state, "pid": m.pid, "starts": m.starts, "last_code": m.last_code}

    def summary_extra(self) -> str:
        return ""

    def final_line(self, status: StatusSource | None) -> str | None:
        """The live line's last words (None: leave it as it was)."""
        return None

    # ------------------------------------------------------------- records
    def event(self, kind: str, **fields) -> None:
        row = {"t": time.time(), "event": kind, **fields}
        with self._events_lock, open(self.paths.supervisor_events, "a") as f:
            f.write(json.dumps(row) + "\n")

    @property
    def events_path(self) -> Path:
        return self.paths.supervisor_events

    def finish(self, code: int, message: str) -> None:
        if self.outcome is None:
            self.outcome = (code, message)

    def summary(self) -> str:
        running = sum(m.state == "running" for m in self.members)
        restarts = sum(max(m.starts - 1, 0) for m in self.members)
        down = [m.spec.name for m in self.members if m.state in self.down_states]
        text = f"{self.member_word} {running}/{len(self.members)} | restarts {restarts}{self.summary_extra()}"
        return text + (f" | {self.down_word} " + ",".join(down) if down else "")

    def write_status(self, status: StatusSource | None) -> None:
        head = {} if self.label == "supervisor" else {"placer": self.label}
        snap = {"t": time.time(), **head, "services": {m.spec.name: self.member_status(m) for m in self.members},
                "status": status.snapshot() if status is not None else {}}
        atomic_write_text(self.paths.status, json.dumps(snap, indent=1, default=str))

    # ------------------------------------------------------------- the run
    def poll(self) -> int | None:
        """One round of the placement's bookkeeping; the exit code once the run is over."""
        self.poll_members()
        if self.outcome is None and not any(m.spec.ends_run for m in self.members) \
                and all(m.state == "done" for m in self.members if m.spec.stop_wave == 0):
            self.finish(0, "all services finished")
        return self.outcome[0] if self.outcome else None

    def wait_ready(self, m: Member, timeout_s: float, give_up: Callable[[], bool]) -> bool:
        """Until ``m``'s ``ready_tcp`` endpoint accepts connections (a ``ready`` event) or not."""
        host, port = m.spec.ready_tcp
        if not wait_tcp_ready(host, port, timeout_s, give_up=give_up):
            return False
        self.event("ready", service=m.spec.name, endpoint=f"{host}:{port}")
        return True

    def shutdown(self, reason: str = "shutdown") -> None:
        """Stop every member, wave by wave (lower ``stop_wave`` first)."""
        self.event("shutdown", reason=reason)
        for wave in sorted({m.spec.stop_wave for m in self.members}):
            self.stop_wave([m for m in self.members if m.spec.stop_wave == wave])

    def run(self, open_status: Callable[[], StatusSource | None] | None = None,
            on_finish: Callable[[StatusSource | None], None] | None = None,
            install_signals: bool = True) -> int:
        """Start everything, watch it until the run ends, a member exhausts its
        restarts, or a signal arrives; always shut down cleanly. Returns the exit code.

        ``open_status`` is called once the members are started (so the driver's own
        Zenoh session opens after every fork); ``on_finish(status)`` runs before the
        shutdown when the run ended normally.
        """
        old = {}
        if install_signals:
            for sig in (signal.SIGINT, signal.SIGTERM):
                old[sig] = signal.signal(sig, lambda signum, _f: self.signals.append(signum))
        status: StatusSource | None = None
        reason = "error"
        live = LiveLine(self.out, self.cfg.status_log_period_s)
        try:
            self.event("supervisor_start", **self.start_fields(), services=[m.spec.name for m in self.members],
                       config=asdict(self.cfg))
            self.start()
            status = open_status() if open_status and self.outcome is None else None
            last_line = time.monotonic()
            while True:
                if self.signals:
                    sig = self.signals[0]
                    self.finish(128 + sig, f"stopped by {signal.Signals(sig).name}")
                    reason = signal.Signals(sig).name
                    break
                if self.outcome is not None or self.poll() is not None:
                    reason = "finished" if self.outcome[0] == 0 else "gave_up"
                    if self.outcome[0] == 0 and on_finish is not None:
                        on_finish(status)
                    break
                if time.monotonic() - last_line >= self.cfg.status_period_s:
                    last_line = time.monotonic()
                    if status is not None:
                        live.show(f"{status.line()} | {self.summary()}")
                    self.write_status(status)
                self.idle()
        except BaseException as exc:
            self.finish(EXIT_GAVE_UP, f"{self.label_error or self.label} error: {exc}")
            self.event("error", message=str(exc))
            raise
        finally:
            self.shutdown(reason)
            self.write_status(status)
            if status is not None:
                status.close()
            live.close(self.final_line(status))
            for sig, handler in old.items():
                signal.signal(sig, handler)
            code, message = self.outcome if self.outcome else (0, "stopped")
            self.event("supervisor_exit", code=code, message=message)
            print(f"{self.label}: {message} (exit code {code}); events in {self.paths.supervisor_events}",
                  file=self.out)
        return code

    def idle(self) -> None:
        """Between two rounds of the loop (a placement whose ``poll_members`` waits itself skips it)."""
        time.sleep(self.cfg.poll_s)
