"""``shield_rtt_ms[B]``: the round trip of one batched request of ``B`` QPs
to the shield (p50/p99), as the process serves it, as a thread on an
in-process session serves it, as the bare ``shield_actions`` call costs it
(``local_qp``), and with the rows an actor sends (``pruned``); the requests
carry the scenario's real safety rows, and their sizes are reported."""
from __future__ import annotations

import time

from common import keys, wire
from common.safety_rows import SafetyRows
from common.shield.qp import shield_actions
from common.spec import JOINT_ACT_DIM
from sage.bench.system.meter import quantiles_ms

WARMUP_REQUESTS = 10   # untimed, before the timed ones of each batch size


def round_trips(bench, bus, run_id: str, batches: dict[int, dict]) -> dict:
    """Per batch size: quantiles of ``bench.cfg.rtt_requests`` timed requests to the shield on ``bus``."""
    out = {}
    for B, body in batches.items():
        samples = []
        for i in range(WARMUP_REQUESTS + bench.cfg.rtt_requests):
            payload = wire.encode("shield_req", body, run_id=run_id, sender="cli/bench", seq=i)
            t0 = time.perf_counter()
            reply = bus.request(keys.shield(run_id), payload, timeout=10.0)
            dt = time.perf_counter() - t0
            if reply is None or reply.ok is None:
                raise RuntimeError(f"shield gave no answer for a batch of {B}: {reply}")
            rep = wire.decode(reply.ok, run_id=run_id, expect="shield_rep")
            if rep.body["a_exec"].shape != (B, JOINT_ACT_DIM):
                raise RuntimeError(f"shield answered shape {rep.body['a_exec'].shape} for {B} problems")
            if i >= WARMUP_REQUESTS:
                samples.append(dt)
        out[B] = quantiles_ms(samples)
    return out


def local_qp(bench, batches: dict[int, dict]) -> dict:
    """Per batch size: quantiles of the same QPs solved by a call in this process."""
    out = {}
    for B, b in batches.items():
        samples = []
        for i in range(WARMUP_REQUESTS + bench.cfg.rtt_requests):
            t0 = time.perf_counter()
            shield_actions(b["a_prop"], SafetyRows.of(b))
            if i >= WARMUP_REQUESTS:
                samples.append(time.perf_counter() - t0)
        out[B] = quantiles_ms(samples)
    return out


def request_bytes(body: dict, run_id: str) -> int:
    return len(wire.encode("shield_req", body, run_id=run_id, sender="a", seq=0))


def table(batches, pruned, process, inprocess, local, pruned_process, run_id: str) -> dict:
    """The ``shield_rtt_ms`` figures, by batch size (a string key, as in JSON)."""
    return {str(B): {"p50": process[B]["p50"], "p99": process[B]["p99"],
                     "inprocess_p50": inprocess[B]["p50"], "inprocess_p99": inprocess[B]["p99"],
                     "local_qp_p50": local[B]["p50"], "local_qp_p99": local[B]["p99"],
                     "pruned_p50": pruned_process[B]["p50"], "pruned_p99": pruned_process[B]["p99"],
                     "bytes": request_bytes(batches[B], run_id),
                     "pruned_bytes": request_bytes(pruned[B], run_id),
                     "requests": process[B]["n"]} for B in batches}
