"""The local placement: a generic process supervisor that runs ``ServiceSpec``
commands, each as its own process group of this host (what SAGE runs is
``deploy/supervised_run.py``). The run's records, loop, signals and shutdown waves
are the run driver's (``deploy/driver.py``), shared with the Ray placement;
what is this placement's own is where and how a member runs and restarts. It:

* restarts a service that crashed (non-zero exit or killed) after an
  exponential backoff, and gives up cleanly -- everything stopped, exit code
  ``EXIT_GAVE_UP``, a one-line reason -- when one service crashes more than
  ``restart_budget`` times within ``restart_window_s`` (no restart storms);
* ends the run when a service marked ``ends_run`` exits 0 (SAGE: the learner
  reached its budget), calling ``on_finish`` first, and stops the rest;
* on SIGINT/SIGTERM sends SIGTERM to every child's process group, waits up to
  ``term_deadline_s``, then SIGKILLs what is left (a second signal skips the
  wait), so no child or grandchild outlives it; children also get SIGTERM from
  the kernel if the supervisor itself is SIGKILLed (``deploy/pdeathsig.py``);
* shows one live status line from a ``StatusSource`` (SAGE: the services'
  heartbeats) and keeps ``status.json`` in the run directory;
* appends its events (start, exit code, backoff, restart, give_up, stop,
  kill, shutdown) as JSONL to ``<run_dir>/supervisor.jsonl``; each child's
  stdout/stderr go to ``<run_dir>/logs/<service>.log``.

The status source is opened only after the children are launched, and
processes start only with ``subprocess`` (fork + exec), so no child ever
inherits a live Zenoh session.
"""
from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from collections import deque
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

from common.status import EXIT_FATAL
from deploy.driver import (EXIT_GAVE_UP, Member, RunDriver, StatusSource, free_tcp_port, kill_group,
                           parent_death_argv, wait_tcp_ready)

__all__ = ["EXIT_GAVE_UP", "ServiceSpec", "StatusSource", "Supervisor", "SupervisorConfig", "free_tcp_port",
           "wait_tcp_ready"]


@dataclass
class SupervisorConfig:
    backoff_initial_s: float = 0.5     # delay before the first restart of a crashed service
    backoff_factor: float = 2.0        # each further consecutive crash multiplies the delay
    backoff_max_s: float = 30.0
    restart_budget: int = 5            # restarts of one service allowed within restart_window_s;
    restart_window_s: float = 300.0    # one crash more and the supervisor gives up
    stable_after_s: float = 60.0       # up this long before a crash: backoff starts over
    term_deadline_s: float = 15.0      # SIGTERM, wait this long, then SIGKILL
    poll_s: float = 0.1
    status_period_s: float = 1.0       # live line and status.json refresh
    status_log_period_s: float = 10.0  # when stderr is not a terminal: one status log line this often
    ready_timeout_s: float = 30.0      # the local router must accept TCP connections by then
    parent_death_signal: bool = True   # children get SIGTERM if the supervisor dies (Linux)

    def validate(self) -> "SupervisorConfig":
        if self.backoff_initial_s < 0 or self.backoff_max_s < self.backoff_initial_s or self.backoff_factor < 1:
            raise ValueError("need 0 <= backoff_initial_s <= backoff_max_s and backoff_factor >= 1")
        if self.restart_budget < 0 or self.restart_window_s <= 0:
            raise ValueError("need restart_budget >= 0 and restart_window_s > 0")
        if self.term_deadline_s < 0 or self.poll_s <= 0:
            raise ValueError("need term_deadline_s >= 0 and poll_s > 0")
        return self

    def backoff(self, consecutive_crashes: int) -> float:
        """Delay before restart number ``consecutive_crashes`` (1, 2, ...)."""
        return min(self.backoff_max_s, self.backoff_initial_s * self.backoff_factor ** (consecutive_crashes - 1))


@dataclass
class ServiceSpec:
    name: str                          # file-safe: "router", "shield", "learner", "actor-0"
    argv: list[str]
    ends_run: bool = False             # exit code 0 of this service ends the run (learner: budget reached)
    stop_wave: int = 0                 # shutdown order: lower waves are stopped first (router last)
    ready_tcp: tuple[str, int] | None = None  # start the next services only once this accepts connections

    def __post_init__(self):
        if not self.name or any(ch in self.name for ch in "/\\ \t\n") or not self.argv:
            raise ValueError(f"bad service spec {self.name!r}: need a file-safe name and a command")


class _Child(Member):
    """One supervised service and its restart bookkeeping."""

    def __init__(self, spec: ServiceSpec):
        super().__init__(spec)         # state: pending, running, backoff, done, failed, stopped
        self.proc: subprocess.Popen | None = None
        self.started = 0.0
        self.crashes = 0               # consecutive crashes (backoff exponent)
        self.restarts: deque[float] = deque()  # restart times within the window (budget)
        self.next_start = 0.0

    @property
    def pid(self) -> int | None:
        return self.proc.pid if self.proc else None


class Supervisor(RunDriver):
    """Runs ``specs`` as child process groups of this machine: the local
    placement of ``deploy.driver.RunDriver`` (which writes the records and runs
    the loop); see the module docstring. ``start()``, ``poll()`` and
    ``shutdown()`` are usable on their own (tests, ``sage bench system``).
    """

    def __init__(self, specs: Sequence[ServiceSpec], run_dir: str | Path, cfg: SupervisorConfig | None = None,
                 *, cwd: str | None = None, env: dict | None = None, out=None):
        super().__init__([_Child(s) for s in specs], run_dir, (cfg or SupervisorConfig()).validate(), out=out)
        self.children: list[_Child] = self.members
        self.log_dir = self.paths.logs
        self.cwd = cwd
        self.env = env

    def child(self, name: str) -> _Child:
        for c in self.children:
            if c.spec.name == name:
                return c
        raise KeyError(name)

    # ------------------------------------------------------------- launching
    def _launch(self, c: _Child) -> None:
        argv = parent_death_argv(c.spec.argv, sys.executable) if self.cfg.parent_death_signal else list(c.spec.argv)
        with open(self.paths.log(c.spec.name), "ab") as log:
            # own session = own process group: a terminal's Ctrl-C reaches only the
            # supervisor, and killpg() reaches the service and anything it spawned
            c.proc = subprocess.Popen(argv, stdin=subprocess.DEVNULL, stdout=log, stderr=subprocess.STDOUT,
                                      start_new_session=True, cwd=self.cwd, env=self.env)
        c.state, c.started = "running", time.monotonic()
        c.starts += 1
        self.event("start", service=c.spec.name, pid=c.proc.pid, attempt=c.starts, argv=c.spec.argv)

    def _wait_ready(self, c: _Child) -> None:
        def exited() -> bool:
            if c.proc.poll() is not None:
                raise RuntimeError(f"{c.spec.name} exited with code {c.proc.returncode} during start-up; "
                                   f"see {self.paths.log(c.spec.name)}")
            return False

        if not self.wait_ready(c, self.cfg.ready_timeout_s, give_up=exited):
            host, port = c.spec.ready_tcp
            raise RuntimeError(f"{c.spec.name} did not accept connections on {host}:{port} "
                               f"within {self.cfg.ready_timeout_s} s")

    def start(self) -> None:
        for c in self.children:
            self._launch(c)
            if c.spec.ready_tcp is not None:
                self._wait_ready(c)

    # ------------------------------------------------------------- monitoring
    def _reaped(self, c: _Child, code: int, how: str = "exit") -> float:
        pid = c.proc.pid
        kill_group(pid, signal.SIGKILL)  # whatever the service left behind in its group
        c.proc, c.last_code = None, code
        uptime = time.monotonic() - c.started
        self.event(how, service=c.spec.name, pid=pid, code=code, uptime_s=round(uptime, 3))
        return uptime

    def _last_line(self, name: str) -> str:
        """The last line a service wrote to its log (its reason for EXIT_FATAL)."""
        try:
            with open(self.paths.log(name), "rb") as f:
                f.seek(max(0, os.fstat(f.fileno()).st_size - 4096))
                lines = [ln for ln in f.read().decode(errors="replace").splitlines() if ln.strip()]
        except OSError:
            lines = []
        return lines[-1].strip()[-600:] if lines else f"exit code {EXIT_FATAL}; see {self.paths.log(name)}"

    def _crashed(self, c: _Child, code: int, uptime: float) -> None:
        now = time.monotonic()
        if uptime >= self.cfg.stable_after_s:
            c.crashes = 0
        c.crashes += 1
        while c.restarts and now - c.restarts[0] > self.cfg.restart_window_s:
            c.restarts.popleft()
        if len(c.restarts) >= self.cfg.restart_budget:
            c.state = "failed"
            msg = (f"giving up: {c.spec.name} crashed {len(c.restarts) + 1} times within "
                   f"{self.cfg.restart_window_s:g} s (last exit code {code}); "
                   f"see {self.paths.log(c.spec.name)}")
            self.event("give_up", service=c.spec.name, code=code, restarts=len(c.restarts), message=msg)
            self.finish(EXIT_GAVE_UP, msg)
            return
        delay = self.cfg.backoff(c.crashes)
        c.restarts.append(now)
        c.state, c.next_start = "backoff", now + delay
        self.event("backoff", service=c.spec.name, code=code, delay_s=delay, consecutive=c.crashes,
                   restarts_in_window=len(c.restarts))

    def poll_members(self) -> None:
        """Reap exits, schedule and perform restarts."""
        for c in self.children:
            if self.outcome is not None:
                break
            if c.proc is not None:
                code = c.proc.poll()
                if code is None:
                    continue
                uptime = self._reaped(c, code)
                if code == 0:
                    c.state = "done"
                    if c.spec.ends_run:
                        self.finish(0, f"{c.spec.name} finished")
                elif code == EXIT_FATAL:   # a fault restarting cannot fix: stop, with the service's own line
                    c.state = "failed"
                    msg = f"{c.spec.name} stopped the run: {self._last_line(c.spec.name)}"
                    self.event("fatal", service=c.spec.name, code=code, message=msg)
                    self.finish(EXIT_FATAL, msg)
                else:
                    self._crashed(c, code, uptime)
            elif c.state == "backoff" and time.monotonic() >= c.next_start:
                self.event("restart", service=c.spec.name, attempt=c.starts + 1)
                self._launch(c)

    # ------------------------------------------------------------- shutdown
    def stop_wave(self, group: list[_Child]) -> None:
        """SIGTERM every running child group of the wave; SIGKILL after the deadline."""
        for c in group:
            if c.state in ("backoff", "pending"):
                c.state = "stopped"  # a pending restart is cancelled
        running = [c for c in group if c.proc is not None]
        for c in running:
            kill_group(c.proc.pid, signal.SIGTERM)
            self.event("stop", service=c.spec.name, pid=c.proc.pid, signal="SIGTERM")
        deadline = time.monotonic() + self.cfg.term_deadline_s
        n_signals = len(self.signals)
        while running and time.monotonic() < deadline and len(self.signals) == n_signals:
            for c in list(running):
                code = c.proc.poll()
                if code is not None:
                    self._reaped(c, code)
                    c.state = "stopped"
                    running.remove(c)
            if running:
                time.sleep(min(self.cfg.poll_s, 0.05))
        for c in running:  # past the deadline (or a second signal): no more waiting
            pid = c.proc.pid
            kill_group(pid, signal.SIGKILL)
            self.event("kill", service=c.spec.name, pid=pid, signal="SIGKILL")
            c.proc.wait()
            self._reaped(c, c.proc.returncode)
            c.state = "stopped"
