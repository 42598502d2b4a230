"""CLI of the learning methods: `sage bench learner`."""
from __future__ import annotations

import json


def register(commands, bench) -> None:
    p = bench.add_parser(
        "learner", help="seconds per learner update for happo, sail_cbf, talo_cbf, sage (ratios to happo)")
    p.add_argument("--json", action="store_true", help="print JSON")
    p.add_argument("--T", type=int, default=64, help="rollout length per env")
    p.add_argument("--K", type=int, default=32, help="envs per batch")
    p.add_argument("--obs-dim", type=int, default=None, help="default: the env's obs_dim (else 40)")
    p.add_argument("--rows", type=int, default=34, help="safety rows M")
    p.add_argument("--repeats", type=int, default=3, help="timed updates per method (median)")
    p.add_argument("--threads", type=int, default=1, help="torch intra-op threads")
    p.add_argument("--seed", type=int, default=0)
    p.set_defaults(func=_bench_handler)


def _bench_handler(args) -> int:
    from common.algos.bench import bench_learner

    out = bench_learner(T=args.T, K=args.K, obs_dim=args.obs_dim, rows=args.rows,
                        repeats=args.repeats, threads=args.threads, seed=args.seed)
    if args.json:
        print(json.dumps(out, indent=2))
    else:
        print(f"learner update, {out['samples']} samples ({out['T']}x{out['K']}), obs_dim {out['obs_dim']}, "
              f"{out['epochs']} epochs x {out['minibatches']} minibatches")
        for name, s in out["update_s"].items():
            print(f"  {name:10s} {s:8.3f} s   {out['ratio_vs_happo'][name]:5.2f}x happo")
    return 0
