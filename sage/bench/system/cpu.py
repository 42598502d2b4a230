"""Where the cores go: CPU seconds of the host's processes, what an env step
costs them, and rates as ratios to the physics bound measured around them."""
from __future__ import annotations

import os

import numpy as np


def process_cpu_s(pid: int) -> float | None:
    """User + system CPU seconds of a live process, all its threads (Linux
    ``/proc/<pid>/stat``, clock-tick resolution); None where unreadable."""
    try:
        with open(f"/proc/{pid}/stat", "rb") as f:
            fields = f.read().rsplit(b")", 1)[1].split()   # the name may hold spaces and ')'
        return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")
    except (OSError, IndexError, ValueError):
        return None


def cpu_budget(cores: dict[str, float], env_steps_per_s: float, host_cpus: int, physics_bound: float) -> dict:
    """What an env step costs the host, from the cores each component used
    while the system made ``env_steps_per_s``: core-microseconds per env step
    by component and in all, and the rate the host's cores would allow at
    that cost if nothing ever waited (``cpu_bound_env_steps_per_s``: host CPUs
    / total cost), also as a fraction of the physics bound. A configuration
    whose CPU bound is below a target cannot reach it by scheduling alone."""
    if not env_steps_per_s > 0 or not cores:
        return {}
    per_step = {k: v / env_steps_per_s * 1e6 for k, v in sorted(cores.items())}
    total = sum(per_step.values())
    bound = host_cpus * 1e6 / total if total > 0 else float("inf")
    return {"cores_used": dict(sorted(cores.items())), "core_us_per_env_step": per_step,
            "core_us_per_env_step_total": total, "cpu_bound_env_steps_per_s": bound,
            "cpu_bound_ratio_to_physics_bound": bound / physics_bound}


def bracketed_ratio(rate: float, before: float, after: float) -> dict:
    """``rate`` against the physics bound measured just before and just after
    it: their mean (``bound``), the ratio to it, and the range from the higher to the lower."""
    if not (before > 0 and after > 0):
        raise ValueError(f"physics bounds must be > 0 (got {before}, {after})")
    bound = (before + after) / 2
    return {"bound": bound, "ratio": rate / bound, "range": [rate / max(before, after), rate / min(before, after)]}


def actor_step_cost(cores: dict[str, float], env_steps_per_s: float, shielded_by_service: bool) -> dict[str, float]:
    """Core-microseconds per env step of one actor-phase window: the actor process's
    own (``actor``) and every process the step needs (``host``): the actor's and the
    router's (chunks and heartbeats), plus the shield's where the actor asks it (an
    idle shield beside a local-QP actor is not counted); the bench's parameter echo
    is left out. Empty when the window has no steps or no CPU reading of the actor."""
    if not env_steps_per_s > 0 or "actor-0" not in cores:
        return {}
    host = sum(v for k, v in cores.items()
               if k in ("actor-0", "router") or (shielded_by_service and k.startswith("shield")))
    return {"actor": cores["actor-0"] / env_steps_per_s * 1e6, "host": host / env_steps_per_s * 1e6}


def median_cost(rounds: list[dict]) -> dict[str, float]:
    """Per figure (``actor``, ``host``), the median over the rounds that have it."""
    names = sorted({k for r in rounds for k in r})
    return {k: float(np.median([r[k] for r in rounds if k in r])) for k in names}


def cpu_ratio(local: list[dict], service: list[dict]) -> float | None:
    """Host cost of an env step with the local QP over that with the shield service
    (medians): the steps/s ratio the same cores would give if nothing waited."""
    a, b = median_cost(local).get("host"), median_cost(service).get("host")
    return a / b if a and b else None
