"""``sage watch RUN``: a live per-carrier leaf-occupancy table and the QP's
correction rate of a running (supervised or multi-host) run, from its actors'
decision-trace stream (``--set actor.trace_every=N`` when the run starts).
An in-process run has no network to subscribe to: watch it from its
``metrics.jsonl`` instead."""
from __future__ import annotations

import sys
import threading
import time
from collections import Counter
from pathlib import Path

from common import keys, wire
from common.audit.live import LiveOccupancy
from common.rundir import RunDir, read_jsonl
from common.status import is_tty
from common.transport import Bus, TlsFiles
from sage.errors import UsageError, one_line, positive_float, positive_int
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


def stale_note(age_s: float | None, period_s: float) -> str:
    """What the table's header adds when no trace came for a while (a run cut off
    without a word: its table stops moving), else nothing."""
    if age_s is None or age_s <= max(5.0, 3 * period_s):
        return ""
    return f"  (no new trace for {age_s:.0f} s)"


def run_ended(run: RunDir, since: float = 0.0) -> str | None:
    """Why the run is over, from its supervisor's events on this host (a
    ``supervisor_exit`` after the last ``supervisor_start``, written at or after
    ``since``, a wall-clock time), or None: still running, or no supervisor here."""
    ended = None
    for event in read_jsonl(run.supervisor_events):
        if event.get("event") == "supervisor_start":
            ended = None
        elif event.get("event") == "supervisor_exit" and float(event.get("t", 0.0)) >= since:
            ended = f"{event.get('message', 'supervisor exited')}, exit code {event.get('code')}"
    return ended


def cmd_watch(args) -> int:
    cfg, endpoints = run_endpoint(args.run, args.connect)
    run = RunDir(args.run)
    over = run_ended(run)
    if over:
        raise UsageError(f"{args.run}: the run has ended ({over}); nothing live to watch "
                         "(its record: metrics.jsonl, summary.json, `sage eval`)")
    live = LiveOccupancy(window=args.window, depth=cfg.algo_config().tree_depth)
    rejected: Counter[str] = Counter()   # by reason: counted and shown, never fatal
    learner_state: dict[str, str] = {}
    last_trace = [None]   # monotonic time of the newest accepted trace
    lock = threading.Lock()

    def on_trace(_key: str, payload: bytes) -> None:
        try:
            msg = wire.decode(payload, run_id=cfg.run_id, expect="trace")
        except wire.WireError as exc:
            rejected[exc.reason] += 1
            return
        with lock:
            try:
                live.add(msg.body)
                last_trace[0] = time.monotonic()
            except ValueError:   # decodes, but cannot be this run's trees (e.g. a leaf out of range)
                rejected["out_of_range"] += 1

    def on_status(_key: str, payload: bytes) -> None:
        try:
            body = wire.decode(payload, run_id=cfg.run_id, expect="status").body
        except wire.WireError:
            return
        if body["role"] == "learner":
            learner_state["state"] = body["state"]

    try:
        bus = Bus.open(connect=list(endpoints), mode="client", tls=TlsFiles.from_transport(cfg.transport), role="cli")
    except Exception as exc:  # noqa: BLE001 - zenoh.ZError: a malformed endpoint or no router there
        raise UsageError(f"cannot reach the run's Zenoh router at {', '.join(endpoints)}: {one_line(exc)} "
                         "(has the run ended? is --connect right?)") from None
    out, tty = sys.stdout, is_tty(sys.stdout)
    drawn = 0
    t_start, t_end = time.time(), time.monotonic() + args.seconds if args.seconds else float("inf")
    try:
        bus.subscribe(keys.trace_all(cfg.run_id), on_trace)
        bus.subscribe(keys.status_all(cfg.run_id), on_status)
        if not cfg.actor.trace_every:
            print(f"note: {args.run} was configured with actor.trace_every = 0; no traces will come "
                  "unless its actors run with --set actor.trace_every=N", file=sys.stderr)
        while time.monotonic() < t_end:
            time.sleep(min(args.period, max(0.0, t_end - time.monotonic())))
            over = run_ended(run, since=t_start) or (
                f"the learner is {learner_state['state']}" if learner_state.get("state") in ("done", "stopped")
                else None)
            if over:
                print(f"run {cfg.run_id} ended ({over}); the last table above is its final state",
                      file=out, flush=True)
                break
            with lock:
                age = None if last_trace[0] is None else time.monotonic() - last_trace[0]
                lines = [f"run {cfg.run_id}  {time.strftime('%H:%M:%S')}{stale_note(age, args.period)}",
                         *live.table()]
            if rejected:
                by_reason = ", ".join(f"{k} {v}" for k, v in sorted(rejected.items()))
                lines.append(f"rejected trace messages: {sum(rejected.values())} ({by_reason})")
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

