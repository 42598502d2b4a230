"""The `sage` command line.

Each command module exposes ``register(commands, bench)``: ``commands`` is
the top-level subparser group (``sage train``, ``sage eval``, ...) and
``bench`` the group under ``sage bench`` (``sage bench qp``, ...). A
registered parser sets ``func=handler``; the handler receives the parsed
namespace and returns an exit code (or None for 0).

Bad user input never ends in a traceback: argparse exits 2 for its own
errors (the ``type=`` helpers of ``sage.errors`` range-check numbers), and a
handler checks the rest of its input (config values, files) inside
``sage.errors.user_input()``; the ``UsageError`` that raises, or a
``SystemExit`` carrying a message, is printed here as one line,
``sage <command>: <message>``, and ``main`` raises ``SystemExit(2)``, as
argparse does for its own errors.
"""
from __future__ import annotations

import argparse
import os
import sys

from sage import audit_commands, compare, env_commands, evaluate, instrument, report, suite, train, watch
from sage.errors import UsageError
from sage.bench import env as bench_env
from sage.bench import learner as bench_learner
from sage.bench import qp as bench_qp
from sage.bench import scaling as bench_scaling
from sage.bench import system as bench_system

# Order is the order of `sage --help`.
COMMAND_MODULES = [
    train,            # sage train, sage up
    evaluate,         # sage eval
    suite,            # sage suite
    instrument,       # sage instrument
    report,           # sage report
    compare,          # sage compare
    env_commands,     # sage env render
    audit_commands,   # sage tree, sage trace, sage audit, sage export-bundle
    watch,            # sage watch
    bench_qp,         # sage bench qp
    bench_env,        # sage bench env, sage bench scripted
    bench_learner,    # sage bench learner
    bench_system,     # sage bench system
    bench_scaling,    # sage bench scaling
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


def command_name(args: argparse.Namespace) -> str:
    """``sage train``, ``sage bench qp``, ``sage env render``, ``sage tree show``, ..."""
    words = [args.command]
    for sub in ("bench_command", "env_command", "action"):
        value = getattr(args, sub, None)
        if isinstance(value, str):
            words.append(value)
    return " ".join(["sage", *filter(None, words)])


def usage_error(args: argparse.Namespace, message: str) -> SystemExit:
    """Print ``sage <command>: <message>`` as one line on stderr; the ``SystemExit(2)`` to raise."""
    prefix = command_name(args)
    text = " ".join(message.split())  # one line, whatever the message held
    if not text.startswith(prefix + ":") and not text.startswith("sage "):
        text = f"{prefix}: {text}"
    print(text, file=sys.stderr)
    return SystemExit(2)


def main(argv: list[str] | None = None) -> int:
    """Run one command; its exit code. Bad input (argparse's or a handler's
    ``UsageError``) raises ``SystemExit(2)`` after one line on stderr."""
    parser = build_parser()
    args = parser.parse_args(argv)   # argparse's own errors: usage + one line, exit 2
    func = getattr(args, "func", None)
    if func is None:
        parser.print_help()
        return 2
    try:
        code = func(args)
    except UsageError as exc:
        if os.environ.get("SAGE_TRACEBACK"):
            raise
        raise usage_error(args, str(exc)) from None
    except SystemExit as exc:
        if not isinstance(exc.code, str):   # sys.exit(n) or argparse inside a handler: as given
            raise
        raise usage_error(args, exc.code) from None
    return int(code or 0)


if __name__ == "__main__":
    sys.exit(main())
