"""Reconciliation under churn (issue 32), in-process and at reduced scale:
two actors stream chunks while the learner is stopped and resumed from its
checkpoints again and again; every chunk an actor sent has exactly one
outcome at the learner, nothing unaccounted and nothing counted twice:

    sum_a (last_seq[a] + 1) = used + stale + incarnation + shape + future
                              + overflow + lost + unused_restart + pending

(``queue_full`` drops are never decoded, so they reappear as ``lost`` gaps and
are not added again), and per actor, sent - (last_seq + 1) >= 0 are the
chunks sent after the final learner stopped listening."""
from __future__ import annotations

import sys
import threading
import time
from pathlib import Path

from prometheus_client import CollectorRegistry

sys.path.insert(0, str(Path(__file__).parent))
from services_fakes import FakeBatchEnv, FakeMethod, fake_propose, fake_solve  # noqa: E402
from conftest import wait_for  # noqa: E402
from test_services import make_cfg  # noqa: E402

from common.transport import Bus  # noqa: E402
from services.actor.service import ActorService  # noqa: E402
from services.learner.service import LearnerService  # noqa: E402
from services.shield.service import ShieldService  # noqa: E402

RESTARTS = 10
IN_SEQUENCE = ("used", "stale", "incarnation", "shape", "future", "overflow", "lost", "unused_restart")


def test_a_checkpoint_counts_the_chunks_a_resumed_learner_will_never_use(tmp_path):
    import numpy as np

    from common import wire

    cfg = make_cfg(tmp_path, max_lag=10)
    first = LearnerService(cfg, None, 0, CollectorRegistry(), threading.Event(), method=FakeMethod())
    first.version = 5
    for seq in range(3):
        body = {"incarnation": first.incarnation, "version": 5, "actor_id": 0,
                "version_t": np.asarray([5], np.int64)}
        first._admit(wire.Message("traj", cfg.run_id, "actor/0", seq, float(seq), body))
    assert len(first.pending) == 3
    first.checkpoint()
    second = LearnerService(cfg, None, 0, CollectorRegistry(), threading.Event(), method=FakeMethod())
    assert second.try_resume()
    assert second.counts["unused_restart"] == 3 and not second.pending
    assert sum(second.counts[k] for k in IN_SEQUENCE) == second.last_seq["actor/0"] + 1


def test_every_chunk_is_accounted_for_across_learner_restarts(tmp_path):
    cfg = make_cfg(tmp_path, updates=10**6, chunk_len=3, checkpoint_every=1, max_lag=1, learner_queue_chunks=8,
                   deploy_probe_every=0)
    bus = Bus.open(inprocess=True)
    stop = threading.Event()
    try:
        shield = ShieldService(cfg, bus, stop=stop, solve=fake_solve)
        threading.Thread(target=shield.run, daemon=True).start()
        actors = [ActorService(cfg, bus, i, stop=stop, env=FakeBatchEnv(2, seed=i), propose=fake_propose)
                  for i in range(cfg.actors)]
        for a in actors:
            threading.Thread(target=a.run, daemon=True).start()
        learner = None
        for _ in range(RESTARTS + 1):   # each learner resumes the previous one's checkpoint
            own = threading.Event()
            learner = LearnerService(cfg, bus, 0, CollectorRegistry(), own, method=FakeMethod())
            th = threading.Thread(target=learner.run, daemon=True)
            th.start()
            wait_for(lambda: learner.state == "running", 30)
            target = learner.updates + 8
            wait_for(lambda: learner.updates >= target, 60)
            own.set()            # stop (the final checkpoint is written); chunks go on meanwhile
            th.join(30)
            assert not th.is_alive()
            time.sleep(0.05)
        stop.set()               # actors stop: whatever they send now is after the finish
        time.sleep(0.2)
        c = learner.counts
        accounted = {s: n + 1 for s, n in learner.last_seq.items()}
        assert sum(c.get(k, 0) for k in IN_SEQUENCE) + len(learner.pending) == sum(accounted.values()), (c, accounted)
        assert c["duplicate"] == c["seq_jump"] == c["actor_restarts"] == 0
        assert c["incarnation"] + c["lost"] + c.get("unused_restart", 0) > 0   # the restarts cost chunks, all counted
        print({"restarts": RESTARTS, "chunks_sent": sum(a.chunks_sent for a in actors), **c})
        for a in actors:
            after_finish = a.chunks_sent - accounted.get(f"actor/{a.actor_id}", 0)
            assert 0 <= after_finish <= 3, (a.actor_id, a.chunks_sent, accounted)
    finally:
        stop.set()
        bus.close()
