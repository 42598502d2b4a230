"""``param_broadcast_ms``: the learner's parameter message (its own
``publish_params``) from publish to decoded in another process (the
``echo`` child, same host, same clock), beside the in-process delivery, and
its size in bytes."""
from __future__ import annotations

import time

import msgpack
import numpy as np

from common import keys, wire
from sage.bench.system.children import ack_key
from sage.bench.system.meter import quantiles_ms

WARMUP_BROADCASTS = 3   # untimed, before the timed ones


def latency(bench, bus, learner, run_id: str, local: bool) -> dict:
    """``bench.cfg.broadcasts`` parameter messages, one at a time; latency publish ->
    decoded, from the echo child's acks or (``local``) a subscriber here."""
    acks: list[dict] = []
    if local:
        def on_params(_k, payload):
            t_recv = time.time()
            msg = wire.decode(payload, run_id=run_id, expect="params")
            acks.append({"seq": msg.seq, "t_sent": msg.t, "t_recv": t_recv, "t_decoded": time.time()})
        bus.subscribe(keys.params(run_id), on_params)
    else:
        bus.subscribe(ack_key(run_id), lambda _k, payload: acks.append(msgpack.unpackb(payload)))
    time.sleep(0.5)  # let the subscriptions propagate through the router
    for i in range(bench.cfg.broadcasts + WARMUP_BROADCASTS):
        n = len(acks)
        learner.version = i
        learner.publish_params()
        deadline = time.monotonic() + 5.0
        while len(acks) == n and time.monotonic() < deadline:
            time.sleep(0.0005)
        time.sleep(0.02)
    lat = [a["t_decoded"] - a["t_sent"] for a in acks[WARMUP_BROADCASTS:]]
    if not lat:
        raise RuntimeError("no parameter broadcast was acknowledged")
    return quantiles_ms(lat)


def message_bytes(learner, run_id: str) -> int:
    """Size of one parameter message of ``learner``'s policy."""
    params = {k: np.asarray(v) for k, v in learner.method.policy_params().items()
              if np.asarray(v).dtype.kind in "fiub"}
    return len(wire.encode("params", {"version": 0, "incarnation": learner.incarnation, "method": "x",
                                      "params": params, "settings": {"kappa": 1.0, "tau": 1.0}},
                           run_id=run_id, sender="learner/0", seq=0))


def figures(process: dict, inprocess: dict, learner, run_id: str) -> dict:
    return {"p50": process["p50"], "p99": process["p99"],
            "inprocess_p50": inprocess["p50"], "inprocess_p99": inprocess["p99"],
            "bytes": message_bytes(learner, run_id), "broadcasts": process["n"]}
