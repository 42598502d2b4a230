"""``router_msgs_per_s``: messages one client publishes as fast as it can,
delivered through the router to another client, per second (``delivered``:
the fraction that arrived): ``small`` (a heartbeat's size) and
``shield_request`` (an actor's request: the batch size nearest
``envs_per_actor``)."""
from __future__ import annotations

import threading
import time

from common import keys
from common.transport import Bus
from sage.bench.system.shield_rtt import request_bytes


def flood_rate(connect: list[str], run_id: str, n: int = 20_000, size: int = 300) -> dict:
    """Messages/s from one client through the router to another."""
    key = f"{keys.run_root(run_id)}/bench/flood"
    got, last, done = [0], [0.0], threading.Event()

    def on_msg(_k, _payload):
        got[0] += 1
        last[0] = time.perf_counter()
        if got[0] == n:
            done.set()

    pub, sub = Bus.open(connect=connect, mode="client"), Bus.open(connect=connect, mode="client")
    try:
        sub.subscribe(key, on_msg)
        time.sleep(0.5)   # the subscription reaches the router
        payload = bytes(size)
        t0 = time.perf_counter()
        for _ in range(n):
            pub.publish(key, payload)
        done.wait(10.0)   # a dropped message never arrives: the rate runs to the last delivery
        dt = max(last[0] - t0, 1e-9)
    finally:
        pub.close()
        sub.close()
    return {"msgs_per_s": got[0] / dt, "delivered": got[0] / n, "bytes": size, "sent": n}


def router_rates(bench, connect: list[str], run_id: str, batches: dict[int, dict]) -> dict:
    """Small (heartbeat-sized) and shield-request-sized messages."""
    near_k = min(batches, key=lambda B: abs(B - bench.cfg.envs_per_actor))   # an actor's request size
    return {"small": flood_rate(connect, run_id),
            "shield_request": flood_rate(connect, run_id, n=2_000, size=request_bytes(batches[near_k], run_id))}
