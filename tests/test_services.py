"""Service loops over a real in-process Zenoh session, with small fakes for
the env, propose step, QP and method (tests/services_fakes.py)."""
import json
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest
from prometheus_client import CollectorRegistry

sys.path.insert(0, str(Path(__file__).parent))
from services_fakes import FakeBatchEnv, FakeMethod, fake_propose, fake_solve  # noqa: E402

from common import keys, wire  # noqa: E402
from common.safety_rows import SafetyRows  # noqa: E402
from common.transport import Bus  # noqa: E402
from services.actor.service import EXIT_UNHEALTHY, ActorService  # noqa: E402
from services.config import ActorConfig, ShieldConfig, TrainConfig  # noqa: E402
from deploy.threads import run_inprocess  # noqa: E402
from services.learner.service import LearnerService  # noqa: E402
from services.shield.service import ShieldService  # noqa: E402
from conftest import wait_for  # noqa: E402


def make_cfg(tmp_path, **kw):
    base = dict(run_id="t1", run_dir=str(tmp_path / "run"), updates=3, chunk_len=6, actors=2,
                envs_per_actor=2, checkpoint_every=2, status_period_s=0.1)
    base.update(kw)
    return TrainConfig(**base).validate()


def sample(registry, name, **labels):
    return registry.get_sample_value(name, labels) or 0.0


def test_inprocess_end_to_end_publishes_versions_and_shields_every_action(tmp_path):
    cfg = make_cfg(tmp_path)
    envs = [FakeBatchEnv(2, seed=0), FakeBatchEnv(2, seed=1)]
    method = FakeMethod()
    reg = CollectorRegistry()
    out = run_inprocess(cfg, progress=False, method=method, envs=envs, propose=fake_propose,
                        solve=fake_solve, registry=reg, timeout_s=60)
    assert out["version"] == 3 and out["updates"] == 3 and method.n == 3
    assert out["chunks"]["used"] == 6 and out["rejected"] == {}
    # every chunk decoded against the schema and batched along K
    for b in method.batches:
        assert b["obs"].shape == (6, 4, 3, 5) and b["last_state"].shape == (4, 6)
        # a_exec is the shield's answer: the fake row a_0 >= 0.5 holds everywhere
        assert (b["a_exec"][..., 0] >= 0.5 - 1e-12).all()
        assert (b["a_prop"][..., 0] < 0.5).any()  # ... and the proposals did need it
    for env in envs:
        assert env.executed and all((a[:, 0] >= 0.5 - 1e-12).all() for a in env.executed)
    run = Path(cfg.run_dir)
    assert (run / "metrics.jsonl").read_text().count("\n") == 3
    for row in map(json.loads, (run / "metrics.jsonl").read_text().splitlines()):
        assert 0.0 <= row["update_cpu_s"] <= row["update_s"] + 0.01   # thread CPU within the wall time
    assert (run / "metrics.csv").read_text().splitlines()[0].startswith("update,version")
    assert sample(reg, "sage_learner_updates_total", role="learner", actor_id="") == 3
    assert sample(reg, "sage_shield_requests_total", role="shield", actor_id="") > 0
    assert out["status"]["learner/0"]["state"] == "done"


def test_two_runs_on_one_session_do_not_cross_talk(bus):
    seen = {"a": [], "b": []}
    bus.subscribe("sage/ra/**", lambda k, p: seen["a"].append(k))
    bus.subscribe("sage/rb/**", lambda k, p: seen["b"].append(k))
    bus.publish(keys.params("ra"), b"x")
    bus.publish(keys.traj("rb", 0), b"y")
    wait_for(lambda: seen["a"] and seen["b"])
    time.sleep(0.05)
    assert seen == {"a": ["sage/ra/params"], "b": ["sage/rb/traj/0"]}
    # and a message that reaches the wrong run anyway is rejected by run id
    payload = wire.encode("control", {"command": "stop", "target": "*"}, run_id="ra", sender="cli/0", seq=0)
    with pytest.raises(wire.WireError) as e:
        wire.decode(payload, run_id="rb")
    assert e.value.reason == "run_id"


def test_a_closed_bus_sends_nothing_and_has_no_replies():
    """An actor thread still stepping while its process shuts the bus: its
    query gets no replies (fail closed: nothing executed), not an exception."""
    closed = Bus.open(inprocess=True)
    closed.close()
    closed.publish(keys.params("r"), b"x")
    assert list(closed.replies(keys.shield("r", 0), b"q", timeout=0.1)) == []


def _req(n, seed):
    env = FakeBatchEnv(n, seed=seed)
    o = env.reset()
    a = np.random.default_rng(seed).uniform(-1, 1, (n, 9))
    return {"a_prop": a, "C": o["C"], "c": o["c"], "row_mask": o["row_mask"], "fixed_mask": o["fixed_mask"]}


def test_shield_micro_batches_and_replies_per_request(tmp_path, bus):
    cfg = make_cfg(tmp_path, shield=ShieldConfig(max_batch=10, window_s=2.0))
    cfg.actors = 4  # four askers: the window may close once all four are queued
    calls, stop, th, shield = _spy_shield(cfg, bus)
    reqs = [_req(n, s) for s, n in enumerate((1, 3, 2, 4))]
    replies = _ask_concurrently(cfg, bus, reqs)
    for r, rep in zip(reqs, replies):
        body = wire.decode(rep.ok, run_id=cfg.run_id, expect="shield_rep").body
        np.testing.assert_allclose(body["a_exec"], fake_solve(r["a_prop"], SafetyRows.of(r)).a_exec)
    # the window closes when max_batch (= all 10 rows) arrived: one solve for four askers
    assert calls == [10]
    cfg.shield.window_s = 0.01  # single requests below: don't wait for company
    # a malformed request gets reply_err, and the shield keeps serving
    rep = bus.request(keys.shield(cfg.run_id), b"\x93garbage", timeout=5.0)
    assert rep.err is not None and rep.err.startswith(b"rejected")
    assert shield.rejected["malformed"] == 1
    rep = bus.request(keys.shield(cfg.run_id), wire.encode("shield_req", reqs[0], run_id=cfg.run_id,
                                                              sender="a", seq=1), timeout=5.0)
    assert rep.ok is not None
    stop.set()
    th.join(5)


def test_shield_solver_error_is_replied_not_raised(tmp_path, bus):
    cfg = make_cfg(tmp_path)

    def broken(*args):
        raise ValueError("NaN in rows")

    stop = threading.Event()
    th = threading.Thread(target=ShieldService(cfg, bus, stop=stop, solve=broken).run, daemon=True)
    th.start()
    p = wire.encode("shield_req", _req(2, 0), run_id=cfg.run_id, sender="a", seq=0)
    wait_for(lambda: (r := bus.request(keys.shield(cfg.run_id), p, timeout=2.0)) is not None
             and r.err is not None and r.err.startswith(b"invalid_input"))
    assert th.is_alive()
    stop.set()
    th.join(5)


def _publish_params(bus, cfg, version=0, incarnation="inc0"):
    m = FakeMethod()
    bus.publish(keys.params(cfg.run_id), wire.encode(
        "params", {"version": version, "incarnation": incarnation, "method": cfg.method,
                   "params": m.policy_params(), "settings": {"kappa": 1.0}},
        run_id=cfg.run_id, sender="learner/0", seq=version))


def test_actor_facing_dead_shield_executes_nothing_and_reports_unhealthy(tmp_path, bus):
    cfg = make_cfg(tmp_path, actor=ActorConfig(shield_timeout_s=0.05, unhealthy_after_s=0.3,
                                               exit_on_unhealthy=True))
    env = FakeBatchEnv(2)
    statuses = []
    bus.subscribe(keys.status(cfg.run_id, "actor", 0),
                  lambda k, p: statuses.append(wire.decode(p, run_id=cfg.run_id).body))
    reg = CollectorRegistry()
    actor = ActorService(cfg, bus, 0, reg, env=env, propose=fake_propose)
    result = {}
    th = threading.Thread(target=lambda: result.update(code=actor.run()), daemon=True)
    th.start()
    wait_for(lambda: actor.state == "waiting")
    _publish_params(bus, cfg)
    th.join(20)
    assert result["code"] == EXIT_UNHEALTHY
    assert env.executed == []                       # the spy env never stepped
    assert actor.shield_failures >= 2
    assert sample(reg, "sage_actor_shield_timeouts_total", role="actor", actor_id="0") == actor.shield_failures
    assert sample(reg, "sage_actor_healthy", role="actor", actor_id="0") == 0
    # status delivery is asynchronous (Zenoh thread)
    wait_for(lambda: any(s["state"] == "unhealthy" and "no shield answer" in s["message"] for s in statuses))


def test_actor_waits_for_late_shield_then_executes_only_filtered(tmp_path, bus):
    cfg = make_cfg(tmp_path, actor=ActorConfig(shield_timeout_s=0.05, unhealthy_after_s=0.2))
    env = FakeBatchEnv(2)
    stop = threading.Event()
    actor = ActorService(cfg, bus, 0, stop=stop, env=env, propose=fake_propose)
    th = threading.Thread(target=actor.run, daemon=True)
    th.start()
    wait_for(lambda: actor.state == "waiting")
    _publish_params(bus, cfg)
    wait_for(lambda: actor.state == "unhealthy")   # unhealthy but not exiting (not configured to)
    assert env.executed == []
    shield = ShieldService(cfg, bus, stop=stop, solve=fake_solve)
    threading.Thread(target=shield.run, daemon=True).start()
    wait_for(lambda: len(env.executed) >= 5)
    assert actor.state == "running"
    stop.set()
    th.join(5)
    assert all((a[:, 0] >= 0.5 - 1e-12).all() for a in env.executed)


def test_unshielded_happo_executes_proposals_without_shield(tmp_path, bus):
    cfg = make_cfg(tmp_path, method="happo")
    env = FakeBatchEnv(2)
    stop = threading.Event()
    actor = ActorService(cfg, bus, 0, stop=stop, env=env, propose=fake_propose)
    th = threading.Thread(target=actor.run, daemon=True)
    th.start()
    wait_for(lambda: actor.state == "waiting")
    _publish_params(bus, cfg)
    wait_for(lambda: len(env.executed) >= 3)
    stop.set()
    th.join(5)
    assert any((a[:, 0] < 0.5).any() for a in env.executed)


def test_learner_counts_rejected_and_stale_chunks_and_keeps_running(tmp_path, bus):
    cfg = make_cfg(tmp_path, updates=100, max_lag=0)
    reg = CollectorRegistry()
    stop = threading.Event()
    learner = LearnerService(cfg, bus, 0, reg, stop, method=FakeMethod())
    th = threading.Thread(target=learner.run, daemon=True)
    th.start()
    wait_for(lambda: learner.state == "running")
    key = keys.traj(cfg.run_id, 0)
    good = wire.encode("control", {"command": "noop", "target": "x"}, run_id=cfg.run_id, sender="a", seq=0)
    bus.publish(key, good[:-3])                                           # truncated
    bus.publish(key, wire.encode("control", {"command": "x", "target": "y"}, run_id="other", sender="a", seq=0))
    bus.publish(key, good)                                                 # wrong kind
    wait_for(lambda: sum(learner.rejected.values()) == 3)
    assert dict(learner.rejected) == {"malformed": 1, "run_id": 1, "kind": 1}
    assert sample(reg, "sage_messages_rejected_total", role="learner", actor_id="", reason="run_id") == 1
    # chunks from another learner incarnation, too old, from the future (versions this
    # learner never published) or with a forged actor id are dropped and counted, not used
    learner.version = 5

    def chunk(seq, version, versions=None, incarnation=None, actor_id=0, sender="actor/0", t=None):
        body = {"incarnation": incarnation or learner.incarnation, "version": version, "actor_id": actor_id,
                "version_t": np.asarray(versions if versions is not None else [version], np.int64)}
        return wire.Message("traj", cfg.run_id, sender, seq, float(seq if t is None else t), body)

    learner._admit(chunk(0, 5, incarnation="someone-else"))
    learner._admit(chunk(1, 4))
    learner._admit(chunk(2, 10**9))
    learner._admit(chunk(3, 5, versions=[5, 10**9]))
    learner._admit(chunk(4, 5, actor_id=7, sender="actor/7"))
    learner._admit(chunk(5, 5, actor_id=0, sender="actor/1"))
    assert learner.counts["incarnation"] == 1 and learner.counts["stale"] == 1 and not learner.pending
    assert learner.counts["future"] == 2 and learner.counts["actor_id"] == 2
    assert learner.counts["lost"] == 0
    learner._admit(chunk(6, 5))                      # actor/0's chunks 4 and 5 never arrived
    assert learner.counts["lost"] == 2 and len(learner.pending) == 1
    learner._admit(chunk(2, 5, t=100.0))             # a restarted actor process starts over at 0 (sent later)
    assert learner.counts["actor_restarts"] == 1 and learner.counts["lost"] == 4
    assert th.is_alive()
    stop.set()
    th.join(5)


def test_shield_with_the_real_qp_matches_a_direct_call(tmp_path, bus):
    from common.shield.qp import solve_cbf_qp

    cfg = make_cfg(tmp_path)
    stop = threading.Event()
    shield = ShieldService(cfg, bus, stop=stop)  # default: common.shield.qp.solve_cbf_qp
    th = threading.Thread(target=shield.run, daemon=True)
    th.start()
    wait_for(lambda: shield.state == "running", timeout=60)
    r = _req(5, 3)
    r["a_prop"][:, 0] = -0.9  # violates the row a_0 >= 0.5
    rep = bus.request(keys.shield(cfg.run_id), wire.encode("shield_req", r, run_id=cfg.run_id, sender="a", seq=0),
                      timeout=10.0)
    body = wire.decode(rep.ok, run_id=cfg.run_id, expect="shield_rep").body
    direct = solve_cbf_qp(r["a_prop"], r["C"], r["c"], r["row_mask"], r["fixed_mask"])
    np.testing.assert_allclose(body["a_exec"], direct.a_exec, atol=1e-12)
    np.testing.assert_allclose(body["a_exec"][:, 0], 0.5, atol=1e-7)
    stop.set()
    th.join(5)


def _spy_shield(cfg, bus):
    """A running shield whose solver records each batch size."""
    calls = []

    def spy_solve(*args):
        calls.append(args[0].shape[0])
        return fake_solve(*args)

    stop = threading.Event()
    shield = ShieldService(cfg, bus, stop=stop, solve=spy_solve)
    th = threading.Thread(target=shield.run, daemon=True)
    th.start()
    wait_for(lambda: shield.state == "running")
    calls.clear()  # drop the warm-up solve
    return calls, stop, th, shield


def _ask_concurrently(cfg, bus, reqs):
    replies = [None] * len(reqs)

    def ask(i):
        p = wire.encode("shield_req", reqs[i], run_id=cfg.run_id, sender=f"actor/{i}", seq=0)
        replies[i] = bus.request(keys.shield(cfg.run_id), p, timeout=5.0)

    ts = [threading.Thread(target=ask, args=(i,)) for i in range(len(reqs))]
    for t in ts:
        t.start()
    for t in ts:
        t.join()
    return replies


def test_shield_window_closes_once_every_actor_asked(tmp_path, bus):
    # A 60 s window would outlast the 5 s request timeout: the answers only
    # arrive because the window closes when one request per actor is queued.
    cfg = make_cfg(tmp_path, shield=ShieldConfig(max_batch=1000, window_s=60.0))
    cfg.actors = 2
    calls, stop, th, _ = _spy_shield(cfg, bus)
    replies = _ask_concurrently(cfg, bus, [_req(n, s) for s, n in enumerate((2, 3))])
    stop.set()
    th.join(timeout=5)
    assert all(r is not None and r.ok is not None for r in replies)
    assert sum(calls) == 5


def test_episode_summary_gives_the_papers_per_update_safety_figures():
    from services.learner.service import _episode_summary

    eps = [{"success": 1.0, "return": 10.0, "collision_steps": 3, "length": 100, "drop": 0.0},
           {"success": 0.0, "return": -2.0, "collision_steps": 0, "length": 200, "drop": 1.0}]
    out = _episode_summary(eps)
    assert out["episodes"] == 2 and out["ep_success_mean"] == 0.5
    assert out["col_per_1k"] == pytest.approx(10.0)   # 3 collision steps in 300 steps
    assert out["drop_rate"] == 0.5
    assert _episode_summary([]) == {"episodes": 0}


def test_replayed_and_far_future_chunks_never_inflate_lost(tmp_path):
    """Issue 32, defect 4: one copy of a real chunk with seq 10**6 added 10**6 to
    ``lost``; three replays added 9 lost chunks that never were."""
    cfg = make_cfg(tmp_path, max_lag=10)
    learner = LearnerService(cfg, None, 0, CollectorRegistry(), threading.Event(), method=FakeMethod())
    learner.version = 5

    def chunk(seq, t, sender="actor/0"):
        body = {"incarnation": learner.incarnation, "version": 5, "actor_id": int(sender[-1]),
                "version_t": np.asarray([5], np.int64)}
        return wire.Message("traj", cfg.run_id, sender, seq, float(t), body)

    for s in range(4):
        learner._admit(chunk(s, 10.0 + s))
    assert len(learner.pending) == 4 and learner.counts["lost"] == 0
    learner._admit(chunk(10**6, 20.0))                 # a copy with a far-future seq
    for s in (1, 2, 3):
        learner._admit(chunk(s, 10.0 + s))             # byte-for-byte replays
    learner._admit(chunk(0, 5.0))                      # an old chunk, not seen here before
    assert learner.counts["lost"] == 0 and learner.counts["actor_restarts"] == 0
    assert learner.counts["seq_jump"] == 1 and learner.counts["duplicate"] == 4
    assert len(learner.pending) == 4                   # none of them is trained on
    learner._admit(chunk(4, 14.0))                     # the real actor goes on, nothing lost
    learner._admit(chunk(7, 17.0))                     # a real gap: 5 and 6 never arrived
    assert learner.counts["lost"] == 2 and learner.last_seq["actor/0"] == 7
    learner._admit(chunk(0, 30.0))                     # a real restart: later, seq starts over
    assert learner.counts["actor_restarts"] == 1 and learner.counts["lost"] == 2
    learner._admit(chunk(cfg.max_seq_gap + 1, 31.0))   # the largest gap still counted
    assert learner.counts["lost"] == 2 + cfg.max_seq_gap


def test_a_chunk_must_arrive_on_its_own_actors_key(tmp_path):
    """The key a chunk came on names its actor: under per-actor TLS certificates only
    actor i may publish traj/<i>, so a chunk there claiming another id is refused."""
    cfg = make_cfg(tmp_path)
    learner = LearnerService(cfg, None, 0, CollectorRegistry(), threading.Event(), method=FakeMethod())
    body = {"incarnation": learner.incarnation, "version": 0, "actor_id": 1, "version_t": np.asarray([0], np.int64)}
    learner._admit(wire.Message("traj", cfg.run_id, "actor/1", 0, 1.0, body), key_id="0")
    assert learner.counts["actor_id"] == 1 and not learner.pending
    learner._admit(wire.Message("traj", cfg.run_id, "actor/1", 0, 1.0, body), key_id="1")
    assert len(learner.pending) == 1
