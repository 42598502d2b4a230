"""`sage eval`, `sage suite`, `sage report`."""
from __future__ import annotations

import argparse
import json
from pathlib import Path


def register(commands, bench) -> None:
    p = commands.add_parser("suite", help="train methods x scenarios x seeds under a budget (resumable)")
    p.add_argument("--methods", default="happo,happo_cbf,talo_cbf,sail_cbf,sage")
    p.add_argument("--scenarios", default="all", help="comma list, a family (LCP/STR/CCN) or 'all'")
    p.add_argument("--seeds", default="0,1")
    p.add_argument("--minutes-per-run", type=float, default=5.0)
    p.add_argument("--updates-per-run", type=int, default=None,
                   help="learner updates per run (same samples for every method); with "
                        "--minutes-per-run, whichever ends first")
    p.add_argument("--eval-episodes", type=int, default=20)
    p.add_argument("--envs-per-actor", type=int, default=32)
    p.add_argument("--set", action="append", default=[], metavar="SECTION.KEY=VALUE",
                   help="passed to every `sage train` (e.g. --set algo.actor_lr=1e-3)")
    p.add_argument("--workers", type=int, default=None, help="parallel runs (default: cores)")
    p.add_argument("--out", default="results/suite")
    p.set_defaults(func=_suite)

    p = commands.add_parser("report", help="Table I (Markdown) and the paper's figures from suite results")
    p.add_argument("results", nargs="+", help="result JSON files or directories holding them")
    p.add_argument("--out", default="results/report")
    p.set_defaults(func=_report)

    p = commands.add_parser("eval", help="deployment evaluation: hard trees + exact QP only")
    p.add_argument("checkpoint", help="run directory or checkpoint file")
    p.add_argument("--episodes", type=int, default=20)
    p.add_argument("--seed", type=int, default=10_000, help="evaluation seeds start here (disjoint from training)")
    p.add_argument("--scenario", default=None, help="override the run's scenario")
    p.add_argument("--unshielded", action="store_true", help="execute the trees' actions without the QP")
    p.add_argument("--human-slot", default=None, choices=["0", "1", "2", "none"],
                   help="deploy beside the scripted human partner in this carrier slot (its block is "
                        "exogenous: noisy, delayed, never corrected by the QP); 'none' = three "
                        "robots; default: the run's own setting")
    p.add_argument("--record", default=None, help="also record decision traces to this file")
    p.add_argument("--json", action="store_true")
    p.set_defaults(func=_eval)


def _scenarios(arg: str) -> list[str]:
    from common.report import FAMILIES

    if arg == "all":
        return [s for f in FAMILIES.values() for s in f]
    out = []
    for part in arg.split(","):
        out += FAMILIES.get(part, [part])
    return out


def _suite(args: argparse.Namespace) -> int:
    from common.suite import SuiteConfig, run_suite

    cfg = SuiteConfig(
        methods=args.methods.split(","), scenarios=_scenarios(args.scenarios),
        seeds=[int(s) for s in args.seeds.split(",")], minutes_per_run=args.minutes_per_run,
        updates_per_run=args.updates_per_run,
        eval_episodes=args.eval_episodes, envs_per_actor=args.envs_per_actor, out_dir=args.out,
        train_overrides=list(args.set),
    )
    if args.workers:
        cfg.workers = args.workers
    run_suite(cfg)
    return 0


def _report(args: argparse.Namespace) -> int:
    from common.report import write_report

    paths = []
    for item in args.results:
        p = Path(item)
        paths += sorted(p.glob("*.json")) if p.is_dir() else [p]
    paths = [p for p in paths if p.name not in ("suite_config.json", "summary.json")]
    out = write_report(paths, Path(args.out))
    print(Path(out["table"]).read_text())
    print(json.dumps(out, indent=2))
    return 0


def _eval(args: argparse.Namespace) -> int:
    from common.deploy_eval import run_eval_command

    return run_eval_command(args)
