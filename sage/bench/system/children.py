"""The bench's own child processes, run under the supervisor:
``python -m sage.bench.system local-actor --config RUN.json --actor-id I``
(the actor with a local QP, the reference of ``ratio_vs_local_qp``) and
``python -m sage.bench.system echo --config RUN.json`` (decodes every
parameter broadcast and acks it). The ack key ``sage/<run>/bench/ack``
(msgpack map ``seq, t_sent, t_recv, t_decoded``) is used by the bench only."""
from __future__ import annotations

import argparse
import signal
import sys
import threading
import time
from dataclasses import replace

import msgpack
import numpy as np

from common import keys, wire
from common.safety_rows import SafetyRows
from common.shield.qp import shield_actions
from common.transport import Bus
from services.actor.service import ActorService
from services.base import run_entry
from services.config import TrainConfig


class LocalQPActor(ActorService):
    """The actor service with the exact joint CBF-QP (Eq. qpshield) solved
    in-process instead of by the shield service: the reference of
    ``ratio_vs_local_qp``. Synchronous (nothing to overlap a local call with)."""

    def __init__(self, cfg, *args, **kw):
        super().__init__(replace(cfg, actor=replace(cfg.actor, pipeline=False)), *args, **kw)

    def filter_actions(self, a_prop, rows: SafetyRows, asked=None):
        t0 = time.perf_counter()
        # the same QP the shield service is asked, so the ratio is the service's cost
        res = shield_actions(a_prop, self.query_rows(a_prop, rows), backend=self.cfg.shield.backend)
        self.rtt.add(time.perf_counter() - t0)
        return np.asarray(res.a_exec, dtype=np.float64), res.status


def ack_key(run_id: str) -> str:
    return f"{keys.run_root(run_id)}/bench/ack"


def echo_main(argv) -> int:
    """Child: decode every parameter broadcast as an actor would, then ack it
    with the publish time, the receive time and the decoded time."""
    parser = argparse.ArgumentParser(prog="python -m sage.bench.system echo")
    parser.add_argument("--config", required=True)
    cfg = TrainConfig.load(parser.parse_args(argv).config)
    stop = threading.Event()
    for sig in (signal.SIGTERM, signal.SIGINT):
        signal.signal(sig, lambda *_: stop.set())
    bus = Bus.open(connect=cfg.transport.connect, mode=cfg.transport.mode)

    def on_params(_key, payload):
        t_recv = time.time()
        try:
            msg = wire.decode(payload, run_id=cfg.run_id, expect="params")
        except wire.WireError as exc:
            print(f"echo: rejected params ({exc.reason})", file=sys.stderr)
            return
        bus.publish(ack_key(cfg.run_id), msgpack.packb(
            {"seq": msg.seq, "t_sent": msg.t, "t_recv": t_recv, "t_decoded": time.time()}))

    try:
        bus.subscribe(keys.params(cfg.run_id), on_params)
        while not stop.wait(0.2):
            pass
    finally:
        bus.close()
    return 0


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    if argv and argv[0] == "local-actor":
        return run_entry("actor", LocalQPActor, argv[1:])
    if argv and argv[0] == "echo":
        return echo_main(argv[1:])
    print("usage: python -m sage.bench.system {local-actor|echo} ... (the benchmark is `sage bench system`)",
          file=sys.stderr)
    return 2
