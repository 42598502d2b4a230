"""Command-line registration of the deploy area: ``sage up`` (supervised
multi-process run, deploy/supervisor.py) and ``sage bench system``
(common/system_bench.py). Listed as ``deploy.cli`` in common/cli.py's
COMMAND_MODULES."""
from __future__ import annotations


def register(commands, bench) -> None:
    from common import system_bench
    from deploy import supervisor

    p = commands.add_parser("up", help="run learner, shield and actors as supervised processes (restarts, "
                                       "clean shutdown, live status)")
    supervisor.add_arguments(p)
    p.set_defaults(func=supervisor.cmd_up)
    system_bench.register(commands, bench)
