"""The `sage` command line.

Each command module exposes ``register(commands, bench)``: ``commands`` is
the top-level subparser group (``sage train``, ``sage eval``, ...) and
``bench`` the group under ``sage bench`` (``sage bench qp``, ...). A
registered parser sets ``func=handler``; the handler receives the parsed
namespace and returns an exit code (or None for 0).
"""
from __future__ import annotations

import argparse
import sys

from sage import audit_commands, env_commands, evaluate, report, suite, train
from sage.bench import env as bench_env
from sage.bench import learner as bench_learner
from sage.bench import qp as bench_qp
from sage.bench import system as bench_system

# Order is the order of `sage --help`.
COMMAND_MODULES = [
    train,            # sage train, sage up
    evaluate,         # sage eval
    suite,            # sage suite
    report,           # sage report
    env_commands,     # sage env render
    audit_commands,   # sage tree, sage trace, sage audit, sage export-bundle
    bench_qp,         # sage bench qp
    bench_env,        # sage bench env, sage bench scripted
    bench_learner,    # sage bench learner
    bench_system,     # sage bench system
]


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="sage",
        description="SAGE: safe, auditable multi-robot cooperative transport training",
    )
    commands = parser.add_subparsers(dest="command", metavar="COMMAND")
    bench_parser = commands.add_parser("bench", help="benchmarks that print JSON with same-run ratios")
    bench = bench_parser.add_subparsers(dest="bench_command", metavar="BENCH")
    for module in COMMAND_MODULES:
        module.register(commands, bench)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    func = getattr(args, "func", None)
    if func is None:
        parser.print_help()
        return 2
    code = func(args)
    return int(code or 0)


if __name__ == "__main__":
    sys.exit(main())
