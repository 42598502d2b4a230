"""Every shield request has a size and a time budget, and service is fair
(issue 32, defect 2): a request larger than the run's spec (the attack: B = 2,
M = 4000 random rows) is refused at decode as a counted ``limit`` without
being solved; one sender's flood gets its own turn and no more; a request
that waited past the actors' timeout is not solved."""
from __future__ import annotations

import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).parent))
from services_fakes import fake_solve, serve_shield  # noqa: E402
from test_services import _req, make_cfg, wait_for  # noqa: E402

from common import keys, wire  # noqa: E402
from services.config import ActorConfig, ShieldConfig  # noqa: E402
from services.shield.service import ShieldService  # noqa: E402


def _attack(M, B=2, seed=0):
    rng = np.random.default_rng(seed)
    return {"a_prop": rng.uniform(-1, 1, (B, 9)), "C": rng.normal(size=(B, M, 9)), "c": rng.normal(size=(B, M)),
            "row_mask": np.ones((B, M), bool), "fixed_mask": np.zeros((B, 9), bool)}


def test_wire_bounds_refuse_symbols_beyond_the_run_spec():
    body = _attack(4000)
    p = wire.encode("shield_req", body, run_id="r", sender="actor/0", seq=0)
    assert len(p) > 600_000                                              # the 650 KB query
    assert wire.decode(p, run_id="r", expect="shield_req").body["C"].shape == (2, 4000, 9)   # no bounds: accepted
    with pytest.raises(wire.WireError) as e:
        wire.decode(p, run_id="r", expect="shield_req", bounds={"M": 34, "B": 256})
    assert e.value.reason == "limit" and "M=4000" in str(e.value)
    with pytest.raises(wire.WireError) as e:
        wire.decode(wire.encode("shield_req", _attack(4, B=300), run_id="r", sender="a", seq=0),
                    run_id="r", expect="shield_req", bounds={"M": 34, "B": 256})
    assert e.value.reason == "limit" and "B=300" in str(e.value)
    ok = wire.decode(wire.encode("shield_req", _attack(34, B=256), run_id="r", sender="a", seq=0),
                     run_id="r", expect="shield_req", bounds={"M": 34, "B": 256})
    assert ok.body["C"].shape == (256, 34, 9)                            # at the bound: kept


def test_the_oversized_query_is_a_counted_limit_and_never_solved(tmp_path, bus):
    cfg = make_cfg(tmp_path)
    solved = []

    def solve(a, rows):
        solved.append(rows.n_rows)
        return fake_solve(a, rows)

    shield, stop, th = serve_shield(cfg, bus, solve)
    solved.clear()
    M = 1500   # the attack at reduced scale: still ~45x the spec's rows, seconds for the real QP
    for i in range(3):
        rep = bus.request(keys.shield(cfg.run_id), wire.encode("shield_req", _attack(M, seed=i), run_id=cfg.run_id,
                                                               sender="actor/0", seq=i), timeout=5.0)
        assert rep is not None and rep.err is not None and rep.err.startswith(b"rejected"), rep
    assert shield.rejected["limit"] == 3 and solved == []
    good = wire.encode("shield_req", _req(2, 0), run_id=cfg.run_id, sender="actor/1", seq=0)
    rep = bus.request(keys.shield(cfg.run_id), good, timeout=5.0)     # the others are still served
    assert rep.ok is not None and solved == [4]
    stop.set()
    th.join(5)


def test_one_senders_flood_cannot_starve_another(tmp_path, bus):
    cfg = make_cfg(tmp_path, shield=ShieldConfig(max_batch=4, window_s=0.0),
                   actor=ActorConfig(shield_timeout_s=60.0))
    release, calls = threading.Event(), []

    def solve(a, rows):
        calls.append(bool((a[:, 1] == 0.77).any()))   # the honest actor's marked proposal
        release.wait(30)
        return fake_solve(a, rows)

    release.set()                                    # the warm-up solve passes
    shield, stop, th = serve_shield(cfg, bus, solve)
    calls.clear()
    release.clear()
    ask = lambda body, sender, seq: bus.replies(  # noqa: E731 - sent now, collected later
        keys.shield(cfg.run_id), wire.encode("shield_req", body, run_id=cfg.run_id, sender=sender, seq=seq),
        timeout=60.0)
    first = ask(_req(2, 0), "actor/flood", 0)
    wait_for(lambda: len(calls) == 1)               # the shield is busy with the flood's first query ...
    flood = [ask(_req(2, i), "actor/flood", i) for i in range(1, 41)]
    wait_for(lambda: shield._queue.qsize() == 40)   # ... while 40 more wait,
    honest = _req(2, 99)
    honest["a_prop"][:, 1] = 0.77
    mine = ask(honest, "actor/1", 0)                # and then the other actor asks once
    wait_for(lambda: shield._queue.qsize() == 41)
    release.set()
    rep = next(iter(mine))
    assert rep.ok is not None
    assert calls[1] is True                         # served in the very next solve, not after 20 of the flood's
    replies = [next(iter(r), None) for r in [first] + flood]
    refused = [r for r in replies if r is not None and r.err is not None]
    assert all(r.err.startswith(b"overloaded") for r in refused)
    assert len(refused) == shield.n_unfair == 40 - cfg.shield.max_pending_per_sender
    assert sum(r.ok is not None for r in replies if r is not None) == 1 + cfg.shield.max_pending_per_sender
    stop.set()
    th.join(5)


def test_a_query_older_than_the_actors_timeout_is_not_solved(tmp_path, bus):
    cfg = make_cfg(tmp_path, shield=ShieldConfig(window_s=0.0), actor=ActorConfig(shield_timeout_s=0.2))
    release, calls = threading.Event(), []

    def solve(a, rows):
        calls.append(len(a))
        release.wait(30)
        return fake_solve(a, rows)

    release.set()                                    # the warm-up solve passes
    shield, stop, th = serve_shield(cfg, bus, solve)
    calls.clear()
    release.clear()
    send = lambda seq, sender: bus.replies(keys.shield(cfg.run_id), wire.encode(  # noqa: E731
        "shield_req", _req(2, seq), run_id=cfg.run_id, sender=sender, seq=seq), timeout=10.0)
    busy = send(0, "actor/0")
    wait_for(lambda: len(calls) == 1)
    late = send(1, "actor/1")
    wait_for(lambda: shield._queue.qsize() == 1)
    time.sleep(0.3)                                  # the waiting query is now past the 0.2 s timeout
    release.set()
    assert next(iter(busy)).ok is not None
    rep = next(iter(late))
    assert rep.err is not None and rep.err.startswith(b"expired")
    assert shield.n_expired == 1 and calls == [2]
    stop.set()
    th.join(5)


class _Req:
    def __init__(self, payload):
        self.payload, self.t_recv, self.errors = payload, time.perf_counter(), []

    def reply_err(self, payload):
        self.errors.append(payload)

    def finish(self):
        pass


def test_a_flood_under_ever_new_sender_names_stays_within_the_queue_bound(tmp_path):
    from prometheus_client import CollectorRegistry

    cfg = make_cfg(tmp_path, shield=ShieldConfig(max_queue=8))
    shield = ShieldService(cfg, None, registry=CollectorRegistry(), stop=threading.Event())
    reqs = [_Req(wire.encode("shield_req", _req(2, i), run_id=cfg.run_id, sender=f"actor/forged{i}", seq=0))
            for i in range(20)]
    for r in reqs:
        shield._admit(r)
    assert shield._n_pending == 8 and len(shield._pending) == 8            # bounded in all, not per name only
    refused = [r for r in reqs if r.errors]
    assert len(refused) == shield.n_unfair == 12 and all(r.errors[0].startswith(b"overloaded") for r in refused)
    assert all(r.payload == b"" for r in reqs)                              # no request keeps its bytes
