"""`sage env render`: the scenarios (several drawn layouts) with a scripted rollout overlaid;
`sage env calibrate`: the scripted controller's outcomes on held-out layouts of every scenario
(clean and biased, shielded and unshielded; common/evaluation/calibration.py)."""
from __future__ import annotations

import json
import math
import time

from common.env.render import render
from common.env.scenarios import SCENARIOS
from sage.errors import nonneg_int, output_file, positive_int


def _render(args):
    output_file(args.out, "--out", figure=True)
    names = list(SCENARIOS) if args.all else [args.scenario]
    records = render(args.out, names, seed=args.seed, layouts=args.layouts)
    for name, rec in records.items():
        print(f"{name}: scripted {'success' if rec['success'] else 'failure'} in {rec['steps']} steps")
    print(f"wrote {args.out}")


def _bounded(lo: float, hi: float):
    def parse(text: str) -> float:
        import argparse

        try:
            v = float(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"not a number: {text!r}") from None
        if not (math.isfinite(v) and lo <= v <= hi):
            raise argparse.ArgumentTypeError(f"must be in [{lo:g}, {hi:g}], got {text}")
        return v

    return parse


def _fmt(v, pct=True):
    if v is None:
        return "-"
    return f"{100 * v:.0f}%" if pct else (f"{v:.1f}" if isinstance(v, float) else str(v))


def _pct1(v):
    return "-" if v is None else f"{100 * v:.1f}%"


def calibration_table(res: dict) -> str:
    """Markdown rows: scenario, arm, SR, drop, truncation, collision episodes, Col./1k pooled,
    QP intervention rate, infeasible steps, episodes."""
    lines = ["| scenario | arm | SR | drop | trunc. | col. ep. | Col./1k | QP interv. | infeas. | episodes |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    for name, arms in res.items():
        for arm, r in arms.items():
            lines.append(f"| {name} | {arm} | {_fmt(r['success_rate'])} | {_fmt(r['drop_rate'])} | "
                         f"{_fmt(r['truncation_rate'])} | {_fmt(r['collision_episode_rate'])} | "
                         f"{r['col_per_1k_pooled']:.1f} | "
                         f"{_pct1(r['intervention_rate'])} | "
                         f"{_fmt(r['infeasible_steps'], pct=False)} | {r['episodes']} |")
    return "\n".join(lines)


def _calibrate(args):
    from common.algos.config import AlgoConfig
    from common.evaluation.calibration import calibrate

    names = list(SCENARIOS) if args.scenario is None else [args.scenario]
    log_std = AlgoConfig().init_log_std   # the default proposal noise
    t0 = time.perf_counter()
    res = calibrate(names, episodes=args.episodes, seed=args.seed, layout_spread=args.layout_spread,
                    aim_offset=args.aim_offset, log_std=log_std)
    if args.json:
        print(json.dumps({"episodes": args.episodes, "seed": args.seed, "layout_spread": args.layout_spread,
                          "aim_offset": args.aim_offset, "log_std": log_std, "scenarios": res}))
    else:
        print(calibration_table(res))
        print(f"({time.perf_counter() - t0:.0f} s; aim offset {args.aim_offset} m, proposal log_std {log_std})")


def register(commands, bench):
    env_p = commands.add_parser("env", help="transport environment tools (render scenarios, calibrate layouts)")
    sub = env_p.add_subparsers(dest="env_command", metavar="ENV_COMMAND")
    r = sub.add_parser("render", help="top-down scenario figure with a scripted rollout overlaid")
    r.add_argument("--scenario", choices=sorted(SCENARIOS), default="maze")
    r.add_argument("--all", action="store_true", help="3x3 grid of all nine scenarios")
    r.add_argument("--out", default="scenario.png")
    r.add_argument("--seed", type=nonneg_int, default=0)
    r.add_argument("--layouts", type=positive_int, default=6,
                   help="drawn layouts (eval stream) overlaid behind the first one's scripted rollout; 1: that one only")
    r.set_defaults(func=_render)

    c = sub.add_parser("calibrate", help="scripted controller (clean / 0.2 m aim bias + proposal noise, shielded / "
                                         "unshielded) on held-out layouts of every scenario")
    c.add_argument("--scenario", choices=sorted(SCENARIOS), default=None, help="one scenario (default: all nine)")
    c.add_argument("--episodes", type=positive_int, default=40, help="episodes (layouts) per scenario and arm")
    c.add_argument("--seed", type=nonneg_int, default=0)
    c.add_argument("--layout-spread", type=_bounded(0.0, 2.0), default=None, help="scale of the stated spreads (default: EnvConfig's)")
    c.add_argument("--aim-offset", type=_bounded(-1.0, 1.0), default=0.2, help="biased arms: aim point this many m left of the route")
    c.add_argument("--json", action="store_true")
    c.set_defaults(func=_calibrate)
