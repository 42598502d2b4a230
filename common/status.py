"""The one-line live status of a run, from the services' heartbeats
(``sage/<run>/status/**``, schema in docs/wire.md). Shared by the in-process
runner and the process supervisor, so both show the same figures."""
from __future__ import annotations


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
