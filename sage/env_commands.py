"""`sage env render`: the scenarios with a scripted rollout overlaid."""
from __future__ import annotations

from common.env.render import render
from common.env.scenarios import SCENARIOS
from sage.errors import nonneg_int, output_file


def _render(args):
    output_file(args.out, "--out", figure=True)
    names = list(SCENARIOS) if args.all else [args.scenario]
    records = render(args.out, names, seed=args.seed)
    for name, rec in records.items():
        print(f"{name}: scripted {'success' if rec['success'] else 'failure'} in {rec['steps']} steps")
    print(f"wrote {args.out}")


def register(commands, bench):
    env_p = commands.add_parser("env", help="transport environment tools (render scenarios)")
    sub = env_p.add_subparsers(dest="env_command", metavar="ENV_COMMAND")
    r = sub.add_parser("render", help="top-down scenario figure with a scripted rollout overlaid")
    r.add_argument("--scenario", choices=sorted(SCENARIOS), default="maze")
    r.add_argument("--all", action="store_true", help="3x3 grid of all nine scenarios")
    r.add_argument("--out", default="scenario.png")
    r.add_argument("--seed", type=nonneg_int, default=0)
    r.set_defaults(func=_render)
