"""Demand pacing: the learner broadcasts its backlog per actor with the
parameters (last admitted chunk, chunks waiting unused) and an actor starts a
chunk only while fewer than ``max_chunks_ahead`` of its own are unsettled, so a
learner slower than its actors no longer drops chunks rolled out for nothing."""
import sys
import threading
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).parent))
from services_fakes import FakeBatchEnv, FakeMethod, fake_propose, fake_solve  # noqa: E402
from test_services import make_cfg, wait_for  # noqa: E402

from common import keys, wire  # noqa: E402
from common.transport import Bus  # noqa: E402
from services.actor.service import ActorService  # noqa: E402
from deploy.threads import run_inprocess  # noqa: E402
from services.learner.service import LearnerService  # noqa: E402
from services.shield.service import ShieldService  # noqa: E402


def _publish(bus, cfg, version, backlog=None):
    body = {"version": version, "incarnation": "inc", "method": cfg.method,
            "params": FakeMethod().policy_params(), "settings": {"kappa": 1.0}}
    if backlog is not None:
        received, waiting = backlog
        body.update(chunks_received=np.asarray(received, np.int64), chunks_waiting=np.asarray(waiting, np.int64))
    bus.publish(keys.params(cfg.run_id), wire.encode("params", body, run_id=cfg.run_id, sender="learner/0",
                                                     seq=version))


def _steady(count, n, settle_s=0.3):
    """The chunk count once it stops growing, asserted to be n."""
    wait_for(lambda: len(count) >= n, timeout=20)
    time.sleep(settle_s)
    assert len(count) == n


def _waiting_actor(tmp_path):
    """One actor (max_chunks_ahead = 2) and a shield on an in-process bus, the actor
    waiting for its first parameters; returns (cfg, bus, stop, actor, chunks it sent)."""
    cfg = make_cfg(tmp_path, chunk_len=4, actors=1, envs_per_actor=2)
    bus, stop = Bus.open(inprocess=True), threading.Event()
    chunks = []
    bus.subscribe(keys.traj_all(cfg.run_id), lambda _k, p: chunks.append(wire.decode(p, run_id=cfg.run_id)))
    threading.Thread(target=ShieldService(cfg, bus, stop=stop, solve=fake_solve).run, daemon=True).start()
    actor = ActorService(cfg, bus, 0, stop=stop, env=FakeBatchEnv(2), propose=fake_propose)
    threading.Thread(target=actor.run, daemon=True).start()
    wait_for(lambda: actor.state == "waiting")
    return cfg, bus, stop, actor, chunks


def test_actor_waits_for_its_unsettled_chunks_not_only_for_new_versions(tmp_path):
    cfg, bus, stop, actor, chunks = _waiting_actor(tmp_path)
    try:
        _publish(bus, cfg, 0, ([-1], [0]))
        _steady(chunks, 2)               # two chunks of version 0 (the version rule)
        _publish(bus, cfg, 1, ([-1], [0]))
        _steady(chunks, 2)               # a new version, but neither chunk is settled: no third
        _publish(bus, cfg, 2, ([0], [1]))
        _steady(chunks, 2)               # chunk 0 admitted, chunk 1 waiting there: still two unsettled
        _publish(bus, cfg, 3, ([1], [0]))
        _steady(chunks, 4)               # both settled: two more
        assert [m.seq for m in chunks] == [0, 1, 2, 3]
        assert [m.body["version"] for m in chunks] == [0, 0, 3, 3]
        _publish(bus, cfg, 4)            # a learner that reports no backlog: the version rule alone
        _steady(chunks, 6)
        assert actor._unsettled(actor.params) == 0
    finally:
        stop.set()
        bus.close()


def test_a_rebroadcast_of_the_held_version_brings_its_newer_backlog(tmp_path):
    """The learner rebroadcasts its parameters with its backlog as it stands; an actor
    that kept the first backlog of a version waited for chunks the learner had long
    admitted, until pace_timeout_s (120 s): seen after router restarts had lost a chunk
    that the learner's batch then waited for."""
    cfg, bus, stop, actor, chunks = _waiting_actor(tmp_path)
    try:
        _publish(bus, cfg, 0, ([-1], [0]))
        _steady(chunks, 2)
        _publish(bus, cfg, 1, ([-1], [0]))
        _steady(chunks, 2)               # version 1, both chunks unsettled
        _publish(bus, cfg, 1, ([1], [0]))
        _steady(chunks, 4)               # the same version again: both settled, two more
    finally:
        stop.set()
        bus.close()


def test_backlog_of_a_new_learner_incarnation_ignores_chunks_sent_to_the_old_one(tmp_path):
    cfg = make_cfg(tmp_path, actors=2)
    actor = ActorService(cfg, Bus.open(inprocess=True), 1)
    actor._sent_chunks.extend([(5, "old", 7), (6, "old", 8), (0, "new", 9)])
    p = {"incarnation": "new", "chunks_received": np.asarray([3, -1]), "chunks_waiting": np.asarray([0, 1])}
    assert actor._unsettled(p) == 2              # seq 9 in flight + one waiting
    p["chunks_received"] = np.asarray([3, 9])
    assert actor._unsettled(p) == 1
    p["chunks_received"] = np.asarray([3])        # a backlog that does not name this actor
    assert actor._unsettled(p) == 0


def test_learner_reports_admitted_and_waiting_chunks_per_actor(tmp_path):
    cfg = make_cfg(tmp_path, actors=3)
    learner = LearnerService(cfg, Bus.open(inprocess=True), method=FakeMethod())
    learner.last_seq = {"actor/0": 4, "actor/2": 1}
    learner.pending.extend([{"actor_id": 2}, {"actor_id": 2}, {"actor_id": 0}])
    out = learner.backlog()
    assert out["chunks_received"].tolist() == [4, -1, 1] and out["chunks_waiting"].tolist() == [1, 0, 2]


class SlowMethod(FakeMethod):
    """A learner update slower than the actors' chunks (the main job's regime)."""

    def update(self, batch, progress):
        time.sleep(0.15)
        return super().update(batch, progress)


def _slow_propose(*args, **kw):
    time.sleep(0.01)   # a chunk of 4 steps takes ~40 ms: slower than the learner's turnaround
    return fake_propose(*args, **kw)


def test_a_slow_learner_gets_fresh_chunks_without_stale_drops(tmp_path):
    cfg = make_cfg(tmp_path, updates=8, chunk_len=4, actors=1)
    out = run_inprocess(cfg, progress=False, method=SlowMethod(), envs=[FakeBatchEnv(2)], propose=_slow_propose,
                        solve=fake_solve, timeout_s=60)
    assert out["updates"] == 8
    # the version rule alone lets 6 of these chunks go stale; a chunk may still go stale
    # when its successor arrives before the learner took it (it then takes the fresher)
    assert out["chunks"].get("stale", 0) <= 2, out["chunks"]
    assert out["actors"][0]["chunks"] <= 8 + 4   # + stale ones, + two rolled out after the last update
