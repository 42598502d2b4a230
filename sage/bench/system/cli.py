"""``sage bench system``: its flags, the run, and the short table it prints
(``--json``: the whole result)."""
from __future__ import annotations

import json
import tempfile
from dataclasses import replace
from pathlib import Path

from common.algos.registry import METHODS
from common.env.scenarios import SCENARIOS
from sage.bench.system.config import QUICK, SystemBenchConfig
from sage.bench.system.driver import SystemBench
from sage.errors import UsageError, int_list, positive_float, positive_int, user_input


def register(commands, bench) -> None:
    d = SystemBenchConfig()
    p = bench.add_parser("system", help="distributed throughput/latency vs in-process (shield RTT, params, steps/s)")
    p.add_argument("--json", action="store_true", help="print the result as JSON (default: a short table)")
    p.add_argument("--quick", action="store_true", help="smallest run (CI smoke): 1 actor, 2 batch sizes, 2 s windows")
    p.add_argument("--scenario", default=d.scenario, choices=sorted(SCENARIOS))
    p.add_argument("--method", default=d.method, choices=METHODS, help="method of the shield/actor phases")
    p.add_argument("--methods", default=",".join(d.methods), help="methods of the whole-system phases, e.g. happo,sage")
    p.add_argument("--shards", default=",".join(map(str, d.shard_counts)), help="shield shard counts, e.g. 1,2")
    p.add_argument("--shard-actors", default=",".join(map(str, d.shard_actor_counts)),
                   help="actor counts of the shard phase, e.g. 2,4")
    p.add_argument("--envs-per-actor", type=positive_int, default=d.envs_per_actor)
    p.add_argument("--actors", default=",".join(map(str, d.actor_counts)), help="actor counts, e.g. 1,2")
    p.add_argument("--batch-sizes", default=",".join(map(str, d.batch_sizes)))
    p.add_argument("--seconds", type=positive_float, default=d.measure_s,
                   help="steady-state window per throughput figure")
    p.add_argument("--work-dir", default=None, help="keep run dirs and service logs here (default: a temp dir)")
    p.add_argument("--out", default=None, help="also write the JSON to this file")
    p.set_defaults(func=cmd_bench_system)


def config_from_args(args) -> SystemBenchConfig:
    cfg = SystemBenchConfig(scenario=args.scenario, method=args.method, envs_per_actor=args.envs_per_actor,
                            actor_counts=tuple(int_list(args.actors, minimum=1, name="--actors")),
                            methods=tuple(m.strip() for m in args.methods.split(",") if m.strip()),
                            shard_counts=tuple(int_list(args.shards, minimum=1, name="--shards")),
                            shard_actor_counts=tuple(int_list(args.shard_actors, minimum=1, name="--shard-actors")),
                            batch_sizes=tuple(int_list(args.batch_sizes, minimum=1, name="--batch-sizes")),
                            measure_s=args.seconds)
    if args.quick:
        cfg = replace(cfg, **QUICK)
    return cfg.validate()


def cmd_bench_system(args) -> int:
    with user_input():
        cfg = config_from_args(args)
    if args.work_dir and Path(args.work_dir).exists() and not Path(args.work_dir).is_dir():
        raise UsageError(f"--work-dir {args.work_dir} exists and is not a directory")
    if args.out and Path(args.out).is_dir():
        raise UsageError(f"--out {args.out} is a directory; give a file name")
    work = Path(args.work_dir) if args.work_dir else Path(tempfile.mkdtemp(prefix="sage-bench-system-"))
    result = SystemBench(cfg, work).run()
    result["work_dir"] = str(work)
    text = json.dumps(result, indent=2)
    if args.out:
        Path(args.out).write_text(text + "\n")
    if args.json:
        print(text)
    else:
        print(summary_table(result))
    return 0


def _share(x) -> str:
    return f"{x:5.2f}" if x is not None else "    -"


def summary_table(r: dict) -> str:
    lines = [f"raw physics bound (1 core): {r['physics_bound_env_steps_per_s']:.0f} env steps/s at the start",
             "env steps/s            multi-process (x bound, learner busy)   in-process (x bound, learner busy)"]
    for method, by_n in r["system"].items():
        first = next(iter(by_n.values()), {})
        if "physics_bound_before" in first:
            lines.append(f"  {method}: physics bound {first['physics_bound_before']:.0f} before, "
                         f"{first['physics_bound_after']:.0f} after its phase; ratios to the mean")
        for n, v in by_n.items():
            note = f"   restarts {v['restarts']}" if v.get("restarts") else ""
            note += f"   in-process failures {v['inprocess_failures']}" if v.get("inprocess_failures") else ""
            lines.append(f"  {method:<9} {n} actor(s) {v['multiprocess']:9.1f} ({v['multiprocess_ratio_to_physics_bound']:.2f}, "
                         f"{_share(v['learner_update_share'])})      {v['inprocess']:9.1f} "
                         f"({v['inprocess_ratio_to_physics_bound']:.2f}, {_share(v['inprocess_learner_update_share'])})"
                         f"{note}")
            for where, budget in (("multi-process", v.get("cpu")), ("in-process", v.get("inprocess_cpu"))):
                if budget:
                    parts = ", ".join(f"{k} {us:.0f}" for k, us in budget["core_us_per_env_step"].items())
                    lines.append(f"      {where} core-us per env step: {parts}; total "
                                 f"{budget['core_us_per_env_step_total']:.0f} -> the host's cores allow "
                                 f"{budget['cpu_bound_env_steps_per_s']:.0f} "
                                 f"({budget['cpu_bound_ratio_to_physics_bound']:.2f} x bound)")
    lines.append("shield shards          actor env steps/s   QPs/s served")
    for k, by_n in r["shards"].items():
        for n, v in by_n.items():
            lines.append(f"  {k} shard(s), {n} actors {v['actor_env_steps_per_s']:12.1f} {v['qps_served']:12.1f}")
    lines.append("shield RTT ms     p50 / p99 (process)   p50 / p99 (in-process)   local QP p50 / p99"
                 "   pruned p50 / p99   bytes full / pruned")
    for B, v in r["shield_rtt_ms"].items():
        lines.append(f"  B={B:<5}        {v['p50']:7.3f} / {v['p99']:7.3f}     {v['inprocess_p50']:7.3f} / "
                     f"{v['inprocess_p99']:7.3f}        {v['local_qp_p50']:7.3f} / {v['local_qp_p99']:7.3f}"
                     f"   {v['pruned_p50']:7.3f} / {v['pruned_p99']:7.3f}   {v['bytes']} / {v['pruned_bytes']}")
    pb = r["param_broadcast_ms"]
    lines.append(f"param broadcast   p50 {pb['p50']:.3f} ms  p99 {pb['p99']:.3f} ms  "
                 f"(in-process {pb['inprocess_p50']:.3f} / {pb['inprocess_p99']:.3f}; {pb['bytes']} B)")
    a = r["actor_steps_per_s"]
    lines.append(f"one actor steps/s: shield service {a['shield_service']:.1f} (pipelined "
                 f"{a['shield_service_pipelined']:.1f}, full rows {a['shield_service_full_rows']:.1f}), "
                 f"local QP {a['local_qp']:.1f}, ratio {r['ratio_vs_local_qp']:.2f} (target >= {r['ratio_target']})")
    cost = r.get("actor_core_us_per_env_step") or {}
    if cost.get("shield_service", {}).get("host") and cost.get("local_qp", {}).get("host"):
        lines.append(f"one actor, core-us per env step (actor process / with router and shield): shield service "
                     f"{cost['shield_service']['actor']:.0f} / {cost['shield_service']['host']:.0f}, local QP "
                     f"{cost['local_qp']['actor']:.0f} / {cost['local_qp']['host']:.0f}; "
                     f"CPU ratio {r['cpu_ratio_vs_local_qp']:.2f}")
    return "\n".join(lines)
