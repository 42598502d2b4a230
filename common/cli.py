"""The `sage` command line.

Each area of the project owns its subcommands in its own module and exposes
``register(commands, bench)``: ``commands`` is the top-level subparser group
(``sage train``, ``sage eval``, ...) and ``bench`` the group under
``sage bench`` (``sage bench qp``, ...). A registered parser sets
``func=handler``; the handler receives the parsed namespace and returns an
exit code (or None for 0).

Modules are imported lazily by name so that `sage --help` stays fast and an
import error in one area names that area instead of breaking every command.
"""
from __future__ import annotations

import argparse
import importlib
import sys

# One line per area; order is the order of `sage --help`.
COMMAND_MODULES = [
    "common.qp_cli",            # sage bench qp
    "common.env.cli",           # sage env render, sage bench env
    "services.cli",             # sage train (in-process), service entry points
    "common.algos.cli",         # sage bench learner
    "common.suite_cli",         # sage eval, sage suite, sage report
    "common.audit.cli",         # sage tree, sage trace, sage audit, sage export-bundle
    "deploy.cli",               # sage up (supervisor), sage bench system
]


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="sage",
        description="SAGE: safe, auditable multi-robot cooperative transport training",
    )
    commands = parser.add_subparsers(dest="command", metavar="COMMAND")
    bench_parser = commands.add_parser("bench", help="benchmarks that print JSON with same-run ratios")
    bench = bench_parser.add_subparsers(dest="bench_command", metavar="BENCH")
    for name in COMMAND_MODULES:
        try:
            module = importlib.import_module(name)
        except ModuleNotFoundError as exc:
            if exc.name == name:  # area not built yet in this checkout
                continue
            raise
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
