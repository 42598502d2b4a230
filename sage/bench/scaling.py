"""``sage bench scaling``: predicted throughput and the first bottleneck at
8, 64 and 512 actor cores, from capacities measured on this machine by
``sage bench system --json`` and ``sage bench learner --json`` (docs/scaling.md).

The model is deliberately plain: every component has a capacity (measured),
a run of ``n`` actor cores asks each for a load (arithmetic), and the
throughput is the smallest capacity. What it leaves out is said in
docs/scaling.md; nothing here is measured at 8+ cores.
"""
from __future__ import annotations

import json
import math
from pathlib import Path

from sage.errors import UsageError

CORES = (8, 64, 512)


def capacities(system: dict, learner: dict) -> dict:
    """The measured inputs of the model, each with where it comes from."""
    actor = system["actor_steps_per_s"]["shield_service"]
    shard = [v for by_n in system["shards"].values() for v in by_n.values() if v.get("qps_per_busy_shard_s")]
    shield_core = max((max(v["qps_per_busy_shard_s"].values()) for v in shard), default=None)
    cpu = learner.get("update_cpu_s") or learner["update_s"]   # thread CPU time per update where reported
    router = system["router_msgs_per_s"]
    cfg = system["config"]
    return {
        "actor_env_steps_per_s_per_core": actor,
        "shield_qps_per_core": shield_core,
        "learner_samples_per_s": {m: learner["samples"] / s for m, s in cpu.items()},
        "learner_time_source": "thread CPU" if learner.get("update_cpu_s") else "wall",
        "router_small_msgs_per_s": router["small"]["msgs_per_s"],
        "router_request_msgs_per_s": router["shield_request"]["msgs_per_s"],
        "params_bytes": system["param_broadcast_ms"]["bytes"],
        "envs_per_actor": cfg["envs_per_actor"], "chunk_len": cfg["chunk_len"],
        "physics_bound_env_steps_per_s": system.get("physics_bound_env_steps_per_s"),
    }


def predict(cap: dict, cores: int, method: str, status_period_s: float = 1.0,
            params_rebroadcast_s: float = 0.5) -> dict:
    """Throughput of ``cores`` actor processes (one each) for ``method``, with
    one learner and one router, and the shards/learners/routers each needs."""
    r, K, T = cap["actor_env_steps_per_s_per_core"], cap["envs_per_actor"], cap["chunk_len"]
    demand = cores * r                                     # env steps/s the actors can make
    learner = cap["learner_samples_per_s"][method]
    # router deliveries per actor per second: a query and its reply per batched step, a chunk
    # and a parameter message per chunk (one chunk per actor per update), the periodic
    # parameter re-broadcast, a heartbeat in and out.
    big = 2 * r / K                                        # shield request-sized (replies are small: counted as big)
    small = 2 * r / (K * T) + 1 / params_rebroadcast_s + 2 / status_period_s
    router_load = cores * (big / cap["router_request_msgs_per_s"] + small / cap["router_small_msgs_per_s"])
    limits = {"actors": demand, "learner (1)": learner, "router (1)": demand / router_load}
    shards = math.ceil(demand / cap["shield_qps_per_core"]) if cap["shield_qps_per_core"] else None
    first = min(limits, key=limits.get)
    return {"cores": cores, "method": method, "env_steps_per_s": limits[first], "first_bottleneck": first,
            "limits": limits, "shield_shards_needed": shards,
            "learners_needed": math.ceil(demand / learner), "routers_needed": math.ceil(router_load),
            "params_mb_per_s_at_router": cores * cap["params_bytes"] * (r / (K * T) + 1 / params_rebroadcast_s) / 1e6}


def table(cap: dict, methods=("happo", "sage"), cores=CORES) -> list[dict]:
    return [predict(cap, n, m) for m in methods if m in cap["learner_samples_per_s"] for n in cores]


def markdown(rows: list[dict]) -> str:
    out = ["| actor cores | method | predicted env steps/s | first bottleneck | shield shards | learners | routers "
           "| params MB/s at router |", "|---|---|---|---|---|---|---|---|"]
    for p in rows:
        out.append(f"| {p['cores']} | {p['method']} | {p['env_steps_per_s']:,.0f} | {p['first_bottleneck']} | "
                   f"{p['shield_shards_needed']} | {p['learners_needed']} | {p['routers_needed']} | "
                   f"{p['params_mb_per_s_at_router']:.1f} |")
    return "\n".join(out)


def register(_commands, bench) -> None:
    p = bench.add_parser("scaling", help="predicted throughput and first bottleneck at 8/64/512 actor cores "
                                         "from measured `bench system` and `bench learner` JSON")
    p.add_argument("--system", required=True, help="`sage bench system --json` output file")
    p.add_argument("--learner", required=True, help="`sage bench learner --json` output file")
    p.add_argument("--json", action="store_true", help="print JSON (default: a markdown table)")
    p.set_defaults(func=cmd_scaling)


def _read(path: str, what: str) -> dict:
    try:
        return json.loads(Path(path).read_text())
    except (OSError, ValueError) as exc:
        raise UsageError(f"--{what} {path}: not a readable JSON file ({exc})") from None


def cmd_scaling(args) -> int:
    system, learner = _read(args.system, "system"), _read(args.learner, "learner")
    try:
        cap = capacities(system, learner)
    except (KeyError, TypeError) as exc:
        raise UsageError(f"missing figure {exc} in the inputs: give full `sage bench system --json` and "
                         "`sage bench learner --json` outputs") from None
    rows = table(cap)
    if args.json:
        print(json.dumps({"measured": cap, "predicted": rows}, indent=2))
    else:
        print(markdown(rows))
    return 0
