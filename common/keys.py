"""Zenoh key space of one run (docs/wire.md): everything lives under
``sage/<run_id>/`` so several runs can share one Zenoh network without
cross-talk. Run and member ids are restricted to a safe alphabet so they can
never inject key-expression wildcards (``*``, ``$``) or extra levels (``/``).
"""
from __future__ import annotations

import re

PREFIX = "sage"
ROLES = ("shield", "actor", "learner", "supervisor", "cli")
_ID_RE = re.compile(r"^[A-Za-z0-9_.\-]{1,64}$")


def check_id(value: str, what: str = "id") -> str:
    value = str(value)
    if not _ID_RE.match(value):
        raise ValueError(f"{what} {value!r} must match {_ID_RE.pattern} (no '/', '*', '$', spaces)")
    return value


def run_root(run_id: str) -> str:
    return f"{PREFIX}/{check_id(run_id, 'run id')}"


def traj(run_id: str, actor_id: int | str) -> str:
    """Trajectory chunks of one actor (pub/sub)."""
    return f"{run_root(run_id)}/traj/{check_id(actor_id, 'actor id')}"


def traj_all(run_id: str) -> str:
    return f"{run_root(run_id)}/traj/*"


def trace(run_id: str, actor_id: int | str) -> str:
    """Thinned decision traces of one actor (pub/sub, ``actor.trace_every``)."""
    return f"{run_root(run_id)}/trace/{check_id(actor_id, 'actor id')}"


def trace_all(run_id: str) -> str:
    return f"{run_root(run_id)}/trace/*"


def params(run_id: str) -> str:
    """Parameter broadcasts from the learner (pub/sub)."""
    return f"{run_root(run_id)}/params"


def shield(run_id: str, shard: int = 0) -> str:
    """Queryable of shield shard ``shard`` (``--shields K``: actor ``i`` asks
    shard ``i % K``): one get per actor step, one reply per get."""
    return f"{run_root(run_id)}/shield/{check_id(shard, 'shield shard')}"


def status(run_id: str, role: str, member_id: int | str) -> str:
    """Heartbeat/status of one service (pub/sub)."""
    if role not in ROLES:
        raise ValueError(f"role {role!r} not in {ROLES}")
    return f"{run_root(run_id)}/status/{role}/{check_id(member_id, 'member id')}"


def status_all(run_id: str) -> str:
    return f"{run_root(run_id)}/status/**"


def control(run_id: str) -> str:
    """Control commands (stop) to every service of the run (pub/sub)."""
    return f"{run_root(run_id)}/control"
