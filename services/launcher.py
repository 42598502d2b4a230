"""What every placement of a run's services shares: which members a run has
(``run_members``), how each is built (``SERVICE_CLASSES``), and the two ways a
member can run. As in Sample Factory, the serial and the parallel runner differ
only in placement, never in what the services do:

* a thread of this process (``ServiceThreads``; the thread placement,
  ``deploy/threads.py``: ``sage train``'s default and CI's);
* a process, the documented entry point
  ``python -m services.<role> --config RUN.json [--actor-id I]``
  (``entry_argv``), placed and restarted by ``deploy/`` (local processes, Ray).
"""
from __future__ import annotations

import logging
import sys
import threading
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

from services.actor.service import ActorService
from services.base import Service
from services.learner.service import LearnerService
from services.shield.service import ShieldService

log = logging.getLogger("sage.launcher")

ROLES = ("shield", "learner", "actor")
SERVICE_CLASSES: dict[str, type[Service]] = {"shield": ShieldService, "learner": LearnerService,
                                             "actor": ActorService}


@dataclass(frozen=True)
class Member:
    role: str
    member_id: int = 0

    @property
    def name(self) -> str:
        """File-safe name (logs, supervisor): ``learner``, ``actor-3``, ``shield``
        (shard 0, the only one of most runs), ``shield-2``."""
        if self.role == "actor" or (self.role == "shield" and self.member_id):
            return f"{self.role}-{self.member_id}"
        return self.role

    @property
    def sender(self) -> str:
        return f"{self.role}/{self.member_id}"


def run_members(actor_ids: Sequence[int], roles: Sequence[str] = ROLES, shields: int = 1) -> list[Member]:
    """The members of a run (or of this host's part of it), shield shards and
    learner first: actors wait for both."""
    bad = set(roles) - set(ROLES)
    if bad:
        raise ValueError(f"unknown roles {sorted(bad)}; choose from {', '.join(ROLES)}")
    out = [Member("shield", k) for k in range(shields)] if "shield" in roles else []
    out += [Member("learner")] if "learner" in roles else []
    if "actor" in roles:
        out += [Member("actor", int(i)) for i in actor_ids]
    return out


def entry_argv(member: Member, config_path: str | Path, python: str = sys.executable) -> list[str]:
    """The process entry point of ``member`` (docs/wire.md)."""
    argv = [python, "-m", f"services.{member.role}", "--config", str(config_path)]
    if member.role == "actor":
        argv += ["--actor-id", str(member.member_id)]
    elif member.role == "shield" and member.member_id:
        argv += ["--shard", str(member.member_id)]
    return argv


class ServiceThreads:
    """Services as daemon threads sharing one stop event; a service that raises
    is logged, recorded in ``errors`` and stops the others (it cannot be restarted)."""

    def __init__(self, stop: threading.Event):
        self.stop = stop
        self.threads: dict[str, threading.Thread] = {}
        self.errors: list[tuple[str, BaseException]] = []
        self.codes: dict[str, int] = {}

    def start(self, svc: Service, stop_all_on_error: bool = True) -> threading.Thread:
        def body():
            try:
                self.codes[svc.sender] = int(svc.run() or 0)
            except BaseException as exc:  # noqa: BLE001 - surfaced by failure()
                log.exception("%s failed", svc.sender)
                self.errors.append((svc.sender, exc))
                if stop_all_on_error:
                    self.stop.set()

        t = threading.Thread(target=body, name=svc.sender, daemon=True)
        self.threads[svc.sender] = t
        t.start()
        return t

    def failure(self, ignore: Sequence[str] = ()) -> tuple[str, BaseException] | None:
        return next(((who, exc) for who, exc in self.errors if who not in ignore), None)

    def join(self, timeout_s: float = 10.0) -> None:
        self.stop.set()
        for t in self.threads.values():
            t.join(timeout=timeout_s)
