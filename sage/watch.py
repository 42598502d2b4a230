"""``sage watch RUN``: a live per-carrier leaf-occupancy table and the QP's
correction rate of a running (supervised or multi-host) run, from its actors'
decision-trace stream (``--set actor.trace_every=N`` when the run starts).
An in-process run has no network to subscribe to: watch it from its
``metrics.jsonl`` instead."""
from __future__ import annotations

import sys
import threading
import time
from pathlib import Path

from common import keys, wire
from common.audit.live import LiveOccupancy
from common.rundir import RunDir
from common.status import is_tty
from common.transport import Bus, TlsFiles
from sage.errors import UsageError, positive_float, positive_int
from sage.runs import read_config


def register(commands, _bench) -> None:
    p = commands.add_parser("watch", help="live leaf occupancy and QP correction rate of a running run")
    p.add_argument("run", help="run directory (runs/<id>) of a supervised or multi-host run")
    p.add_argument("--connect", action="append", default=None,
                   help="Zenoh router endpoint (default: the run's, from its config)")
    p.add_argument("--window", type=positive_int, default=200, help="recent traces the table is over")
    p.add_argument("--period", type=positive_float, default=1.0, help="seconds between redraws")
    p.add_argument("--seconds", type=positive_float, default=None, help="stop after this long (default: Ctrl-C)")
    p.set_defaults(func=cmd_watch)


def run_endpoint(run_dir: str | Path, connect: list[str] | None):
    """(config, router endpoints) of the run at ``run_dir``; a ``UsageError``
    if it is not a run directory or has no network to watch."""
    run = RunDir(run_dir)
    path = run.supervised_config if run.supervised_config.exists() else run.config
    if not path.exists():
        raise UsageError(f"{run_dir}: not a run directory (no config.json)")
    try:
        cfg = read_config(path)
    except (ValueError, TypeError) as exc:
        raise UsageError(f"{path}: not a readable run config ({exc})") from None
    endpoints = connect or cfg.transport.connect
    if not endpoints:
        raise UsageError(f"{run_dir}: an in-process run has no network to watch; start it with `sage up` or "
                         "`sage train --mode supervised`, or give --connect")
    return cfg, endpoints


def cmd_watch(args) -> int:
    cfg, endpoints = run_endpoint(args.run, args.connect)
    live = LiveOccupancy(window=args.window)
    rejected = [0]
    lock = threading.Lock()

    def on_trace(_key: str, payload: bytes) -> None:
        try:
            msg = wire.decode(payload, run_id=cfg.run_id, expect="trace")
        except wire.WireError:
            rejected[0] += 1   # counted and shown, never fatal
            return
        with lock:
            live.add(msg.body)

    bus = Bus.open(connect=list(endpoints), mode="client", tls=TlsFiles.from_transport(cfg.transport), role="cli")
    out, tty = sys.stdout, is_tty(sys.stdout)
    drawn = 0
    t_end = time.monotonic() + args.seconds if args.seconds else float("inf")
    try:
        bus.subscribe(keys.trace_all(cfg.run_id), on_trace)
        if not cfg.actor.trace_every:
            print(f"note: {args.run} was configured with actor.trace_every = 0; no traces will come "
                  "unless its actors run with --set actor.trace_every=N", file=sys.stderr)
        while time.monotonic() < t_end:
            time.sleep(min(args.period, max(0.0, t_end - time.monotonic())))
            with lock:
                lines = [f"run {cfg.run_id}  {time.strftime('%H:%M:%S')}", *live.table()]
            if rejected[0]:
                lines.append(f"rejected trace messages: {rejected[0]}")
            if tty and drawn:
                out.write(f"\x1b[{drawn}F\x1b[J")   # redraw the table in place
            out.write("\n".join(lines) + "\n")
            out.flush()
            drawn = len(lines)
    except KeyboardInterrupt:
        pass
    finally:
        bus.close()
    return 0

