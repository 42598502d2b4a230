"""Exec a command that receives SIGTERM when its parent (the supervisor) dies.

    python -m deploy.pdeathsig PARENT_PID -- COMMAND [ARGS...]

The supervisor normally stops its children itself; this covers the case it
cannot: the supervisor killed with SIGKILL (or crashing). Linux keeps the
parent-death signal across ``exec``, so the service runs unchanged. The
supervisor cannot set it with ``preexec_fn`` because that is unsafe in a
process with threads (its Zenoh session). Elsewhere than Linux it just execs.
"""
from __future__ import annotations

import ctypes
import os
import signal
import sys

PR_SET_PDEATHSIG = 1


def set_parent_death_signal(sig: int = signal.SIGTERM) -> bool:
    """Ask the kernel to send ``sig`` to this process when its parent exits."""
    if not sys.platform.startswith("linux"):
        return False
    libc = ctypes.CDLL(None, use_errno=True)
    if libc.prctl(PR_SET_PDEATHSIG, int(sig), 0, 0, 0) != 0:
        raise OSError(ctypes.get_errno(), "prctl(PR_SET_PDEATHSIG) failed")
    return True


def main(argv: list[str]) -> int:
    if len(argv) < 3 or argv[1] != "--":
        print("usage: python -m deploy.pdeathsig PARENT_PID -- COMMAND [ARGS...]", file=sys.stderr)
        return 2
    parent, command = int(argv[0]), argv[2:]
    armed = set_parent_death_signal()
    if armed and os.getppid() != parent:
        return 1  # the parent died before the signal was armed: do not start an orphan
    os.execvp(command[0], command)
    return 127  # not reached


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
