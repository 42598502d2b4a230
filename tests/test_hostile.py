"""Hostile peers and floods, in-process (issue: services that survive hostile
input): forged and uncertified shield answers are refused and never executed,
parameters that cannot drive the trees are refused, chunks from the future are
dropped, every bounded queue counts its drops and memory stays bounded, and a
learner restart never reuses a version nor double-logs an update."""
from __future__ import annotations

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
from test_services import make_cfg, sample, wait_for  # noqa: E402

from common import keys, wire  # noqa: E402
from common.safety_rows import SafetyRows  # noqa: E402
from common.shield.verify import verify_answer  # noqa: E402
from services.actor.service import ActorService  # noqa: E402
from services.config import ActorConfig, ShieldConfig  # noqa: E402
from services.learner.service import LearnerService  # noqa: E402
from services.shield.service import ShieldService  # noqa: E402


def _envs(pipelined: bool):
    """One fake env, or a pipelined actor's two env groups (2 and 1 envs)."""
    return [FakeBatchEnv(2, seed=0), FakeBatchEnv(1, seed=1)] if pipelined else FakeBatchEnv(2)


def _executed(env) -> list[np.ndarray]:
    return [a for e in (env if isinstance(env, list) else [env]) for a in e.executed]


PIPELINED = pytest.mark.parametrize("pipelined", [False, True], ids=["sync", "pipelined"])


def _started_actor(cfg, bus, stop, env, registry=None):
    """An actor thread with the fake env(s) and propose step, waiting for parameters."""
    actor = ActorService(cfg, bus, 0, registry, stop=stop, env=env, propose=fake_propose)
    th = threading.Thread(target=actor.run, daemon=True)
    th.start()
    wait_for(lambda: actor.state == "waiting")
    return actor, th


def _publish_params(bus, cfg, params=None, version=0, method=None):
    m = FakeMethod()
    body = {"version": version, "incarnation": "inc", "method": method or cfg.method,
            "params": params if params is not None else m.policy_params(), "settings": {"kappa": 1.0}}
    bus.publish(keys.params(cfg.run_id), wire.encode("params", body, run_id=cfg.run_id, sender="learner/0", seq=version))


def _forged_shield(bus, cfg, answer, stop):
    """A second queryable on the shield key answering every request with ``answer(body)``."""
    q = bus.serve(keys.shield(cfg.run_id))

    def loop():
        n = 0
        while not stop.is_set():
            try:
                req = q.get(timeout=0.05)
            except Exception:  # noqa: BLE001 - queue.Empty
                continue
            body = wire.decode(req.payload, run_id=cfg.run_id, expect="shield_req").body
            a_exec, status = answer(body)
            B = len(a_exec)
            req.reply(wire.encode("shield_rep", {"a_exec": a_exec, "status": status, "correction_norm": np.zeros(B),
                                                 "slack": np.zeros(B), "batch_size": B, "solve_s": 0.0},
                                  run_id=cfg.run_id, sender="shield/forged", seq=n))
            n += 1

    t = threading.Thread(target=loop, daemon=True)
    t.start()
    return t


RAW = ("raw proposal", lambda b: (b["a_prop"], np.zeros(len(b["a_prop"]), np.int32)))
MAX_ITER = ("status 2", lambda b: (fake_solve(b["a_prop"], SafetyRows.of(b)).a_exec, np.full(len(b["a_prop"]), 2)))
CLAIMS_INFEASIBLE = ("raw, claimed infeasible",
                     lambda b: (np.clip(b["a_prop"], -1, 1), np.ones(len(b["a_prop"]), np.int32)))
# a plausible forgery: every row met, in the box, status optimal, but not the projection
# (the fake env's one row is a_0 >= 0.5: "all zeros" moved onto it)
SAFE_NOT_QP = ("safe point, claimed optimal",
               lambda b: (np.eye(len(b["a_prop"][0]))[[0] * len(b["a_prop"])] * 0.5, np.zeros(len(b["a_prop"]), np.int32)))


@PIPELINED
@pytest.mark.parametrize("forger", [RAW, MAX_ITER, CLAIMS_INFEASIBLE, SAFE_NOT_QP], ids=lambda f: f[0])
def test_forged_shield_alone_gets_nothing_executed(tmp_path, bus, forger, pipelined):
    cfg = make_cfg(tmp_path, actor=ActorConfig(shield_timeout_s=0.1, unhealthy_after_s=30))
    stop = threading.Event()
    _forged_shield(bus, cfg, forger[1], stop)
    env, reg = _envs(pipelined), CollectorRegistry()
    actor, th = _started_actor(cfg, bus, stop, env, reg)
    _publish_params(bus, cfg)
    wait_for(lambda: sum(actor.answers_refused.values()) >= 5)
    stop.set()
    th.join(5)
    assert actor.pipelined == pipelined
    assert _executed(env) == []                    # fail closed: nothing ran
    refused = sum(actor.answers_refused.values())
    metric = sum(sample(reg, "sage_actor_shield_answers_rejected_total", role="actor", actor_id="0", reason=r)
                 for r in ("rows", "status", "infeasible_claim", "kkt"))
    assert metric == refused >= 5


@PIPELINED
def test_forged_shield_beside_the_real_one_is_harmless(tmp_path, bus, pipelined):
    cfg = make_cfg(tmp_path, chunk_len=1000, actor=ActorConfig(shield_timeout_s=0.5))  # no learner: one long chunk
    stop = threading.Event()
    _forged_shield(bus, cfg, RAW[1], stop)
    shield = ShieldService(cfg, bus, stop=stop, solve=fake_solve)
    threading.Thread(target=shield.run, daemon=True).start()
    env = _envs(pipelined)
    actor, th = _started_actor(cfg, bus, stop, env)
    _publish_params(bus, cfg)
    wait_for(lambda: len(_executed(env)) >= 40, timeout=30)
    stop.set()
    th.join(5)
    assert all((a[:, 0] >= 0.5 - 1e-9).all() for a in _executed(env))   # only filtered actions ran
    assert sum(actor.answers_refused.values()) > 0                   # the forger was heard, and refused


def test_verify_answer_accepts_a_genuine_infeasible_answer():
    from common.shield.qp import shield_actions

    # a_0 >= 0.5 and -a_0 >= 0.5 cannot both hold: the slack QP answer is the least violation
    C = np.zeros((1, 2, 9))
    C[0, 0, 0], C[0, 1, 0] = 1.0, -1.0
    rows = SafetyRows(C, np.full((1, 2), 0.5), np.ones((1, 2), bool), np.zeros((1, 9), bool))
    a = np.full((1, 9), 0.3)
    res = shield_actions(a, rows)
    assert res.status[0] == 1
    assert verify_answer(a, rows, res.a_exec, res.status) is None
    worse = res.a_exec.copy()
    worse[0, 0] = 0.9                                  # violates the second row by more than needed
    assert verify_answer(a, rows, worse, res.status) == "rows"
    fixed = SafetyRows(C, rows.c, rows.row_mask, np.eye(9, dtype=bool)[[1]])
    moved = res.a_exec.copy()
    moved[0, 1] += 0.1                                 # the human's block was changed
    assert verify_answer(a, fixed, moved, res.status) == "fixed_block"


def test_params_that_do_not_fit_the_trees_are_refused(tmp_path, bus):
    cfg = make_cfg(tmp_path, chunk_len=1000)   # no learner: one long chunk, no pacing wait
    stop = threading.Event()
    shield = ShieldService(cfg, bus, stop=stop, solve=fake_solve)
    threading.Thread(target=shield.run, daemon=True).start()
    env, reg = FakeBatchEnv(2), CollectorRegistry()
    actor, th = _started_actor(cfg, bus, stop, env, reg)
    good = FakeMethod().policy_params()
    bad_shape = dict(good, **{"carrier_1/K": np.zeros((2, 3, 99), np.float32)})
    _publish_params(bus, cfg, bad_shape, version=7)                   # passes the wire check only
    _publish_params(bus, cfg, {"carrier_0/W": np.ones((1, 5))}, version=8)
    _publish_params(bus, cfg, good, version=9, method="happo")      # another method's trees
    wait_for(lambda: actor.params_refused == 3)
    assert actor.params is None and env.executed == []
    _publish_params(bus, cfg, good, version=1)
    wait_for(lambda: len(env.executed) >= 3)
    _publish_params(bus, cfg, bad_shape, version=2)
    wait_for(lambda: actor.params_refused == 4)
    n = len(env.executed)
    wait_for(lambda: len(env.executed) >= n + 3)                     # still running on version 1
    assert actor.params["version"] == 1 and th.is_alive()
    assert sample(reg, "sage_actor_params_rejected_total", role="actor", actor_id="0") == 4
    stop.set()
    th.join(5)


def _rss_mb() -> float:
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024
    return 0.0


@pytest.mark.slow
def test_flood_of_future_chunks_and_shield_queries_keeps_memory_bounded(tmp_path, bus):
    """Future-version chunks and shield queries at full speed for FLOOD_S seconds:
    the learner drops them (counted), the shield answers or refuses each one, and
    the process's RSS stays within a fixed bound."""
    FLOOD_S, RSS_BOUND_MB = 30.0, 400.0
    cfg = make_cfg(tmp_path, updates=10**6, learner_queue_chunks=16, shield=ShieldConfig(max_queue=2))
    stop = threading.Event()
    learner = LearnerService(cfg, bus, 0, stop=stop, method=FakeMethod())
    shield = ShieldService(cfg, bus, stop=stop, solve=fake_solve)
    for svc in (learner, shield):
        threading.Thread(target=svc.run, daemon=True).start()
    wait_for(lambda: learner.state == "running" and shield.state == "running", timeout=30)
    T, K, M, O, S = 32, 32, 34, 34, 60                             # a real chunk's size (~1.5 MB)
    r = np.random.default_rng(0)
    body = {"actor_id": 0, "version": 10**9, "incarnation": learner.incarnation, "env_steps": 1,
            "version_t": np.full(T, 10**9), "obs": r.normal(size=(T, K, 3, O)).astype(np.float32),
            "state": np.zeros((T, K, S), np.float32), "C": np.zeros((T, K, M, 9)), "c": np.zeros((T, K, M)),
            "row_mask": np.zeros((T, K, M), bool), "fixed_mask": np.zeros((T, K, 9), bool),
            **{k: np.zeros((T, K, 9)) for k in ("a_st", "a_bar", "a_prop", "a_exec")},
            "shield_status": np.zeros((T, K), np.int32), "logp": np.zeros((T, K, 3)),
            "leaf": np.zeros((T, K, 3), np.int64), "reward": np.zeros((T, K)),
            "terminated": np.zeros((T, K), bool), "truncated": np.zeros((T, K), bool),
            "final_state": np.zeros((T, K, S), np.float32), "final_obs": np.zeros((T, K, 3, O), np.float32),
            "last_state": np.zeros((K, S), np.float32), "last_obs": np.zeros((K, 3, O), np.float32), "episodes": []}
    req = wire.encode("shield_req", {"a_prop": np.zeros((32, 9)), **SafetyRows.of(FakeBatchEnv(32).reset()).as_dict()},
                      run_id=cfg.run_id, sender="actor/0", seq=0)
    rss0, peak, sent, answered, samples = _rss_mb(), 0.0, 0, [0], []
    asked = threading.Event()

    def ask():
        while not asked.is_set():
            for rep in bus.replies(keys.shield(cfg.run_id), req, timeout=1.0):
                answered[0] += 1
    askers = [threading.Thread(target=ask, daemon=True) for _ in range(8)]
    for t in askers:
        t.start()
    try:
        t0 = time.monotonic()
        t_end = t0 + FLOOD_S
        while time.monotonic() < t_end:
            bus.publish(keys.traj(cfg.run_id, 0), wire.encode("traj", body, run_id=cfg.run_id, sender="actor/0",
                                                              seq=sent))
            sent += 1
            rss = _rss_mb()
            peak = max(peak, rss)
            if time.monotonic() - t0 > len(samples) * FLOOD_S / 6:
                samples.append(round(rss))
    finally:
        asked.set()
        for t in askers:
            t.join(5)
    def received():
        return learner.counts["future"] + learner.counts["queue_full"]
    wait_for(lambda: received() == sent, timeout=30)                  # every chunk accounted for
    stop.set()
    print(json.dumps({"flood_s": FLOOD_S, "chunks_sent": sent, "future_dropped": learner.counts["future"],
                      "queue_full_dropped": learner.counts["queue_full"], "shield_answers": answered[0],
                      "shield_overloaded": shield.n_dropped, "rss_start_mb": rss0, "rss_peak_mb": peak,
                      "rss_samples_mb": samples}))
    assert learner.updates == 0 and not learner.pending              # nothing forged was trained on
    assert answered[0] > 0 and shield.n_dropped > 0          # answered, or refused at once and counted
    assert peak - rss0 < RSS_BOUND_MB, (rss0, peak)
    # bounded, not merely slow to grow: the second half of the flood adds little
    assert samples[-1] - samples[len(samples) // 2] < 0.25 * RSS_BOUND_MB, samples


def test_learner_restart_never_reuses_a_version_nor_double_logs_an_update(tmp_path):
    """A learner killed after update 4 whose newest checkpoint is update 2 (and whose
    last metrics line is torn): the next incarnation resumes from update 2, publishes
    versions above every one published before, and metrics.jsonl holds each update once."""
    from deploy.threads import run_inprocess
    from services_fakes import FakeBatchEnv as Env

    def run(updates):
        cfg = make_cfg(tmp_path, updates=updates, actors=1, checkpoint_every=2)
        return run_inprocess(cfg, progress=False, method=FakeMethod(), envs=[Env(2)], propose=fake_propose,
                             solve=fake_solve, timeout_s=60)

    run_dir = tmp_path / "run"
    first = run(4)
    assert first["version"] == 4
    (run_dir / "checkpoints" / "ckpt_00000004.pt").unlink()          # the kill came before that checkpoint
    with open(run_dir / "metrics.jsonl", "a") as f:
        f.write('{"update": 5, "vers')                                 # and cut a line short
    second = run(6)
    assert second["resumed_from"] == 2 and second["updates"] == 6
    rows = [json.loads(x) for x in (run_dir / "metrics.jsonl").read_text().splitlines()]
    assert [r["update"] for r in rows] == [1, 2, 3, 4, 5, 6]
    versions = [r["version"] for r in rows]
    assert versions == sorted(set(versions))                            # strictly increasing
    assert min(versions[2:]) > first["version"]                         # no version published twice
    discarded = [json.loads(x) for x in (run_dir / "metrics_discarded.jsonl").read_text().splitlines()]
    assert [r["update"] for r in discarded] == [3, 4] and all(r["resumed_from"] == 2 for r in discarded)
    csv_lines = (run_dir / "metrics.csv").read_text().splitlines()
    assert len(csv_lines) == 1 + 6


def _live_run(tmp_path, bus, **kw):
    """A learner (fake method), a shield (fake QP) and one actor, running."""
    cfg = make_cfg(tmp_path, updates=10**6, actors=1, **kw)
    stop = threading.Event()
    method = FakeMethod()
    learner = LearnerService(cfg, bus, 0, stop=stop, method=method)
    shield = ShieldService(cfg, bus, stop=stop, solve=fake_solve)
    for svc in (learner, shield):
        threading.Thread(target=svc.run, daemon=True).start()
    env = FakeBatchEnv(2)
    actor, th = _started_actor(cfg, bus, stop, env)
    return cfg, stop, learner, actor, th, method


def _forged_params(cfg, learner, method, version):
    """The live learner's identity, incarnation and trees, with another version."""
    body = {"version": version, "incarnation": learner.incarnation, "method": cfg.method,
            "params": method.policy_params(), "settings": {"kappa": 1.0}}
    return wire.encode("params", body, run_id=cfg.run_id, sender="learner/0", seq=10**6)


def test_a_forged_version_jump_is_fenced_and_actors_keep_following_the_learner(tmp_path, bus):
    """Issue 32, defect 3: version 10**12 with the live learner's identity froze training."""
    cfg, stop, learner, actor, th, method = _live_run(tmp_path, bus)
    wait_for(lambda: actor.params is not None and learner.version >= 2
             and getattr(actor, "_vouched", 0) is not None, timeout=30)
    bus.publish(keys.params(cfg.run_id), _forged_params(cfg, learner, method, 10**12))
    v = learner.version
    wait_for(lambda: v + 2 <= actor.params["version"] < 10**12, timeout=20)   # still following the real learner
    assert actor.params_fenced == 1
    assert actor.params["version"] < 10**12 and actor.params["incarnation"] == learner.incarnation
    assert actor.status_fields()["extra"]["params_fenced"] == 1.0
    stop.set()
    th.join(5)


def test_a_forged_version_inside_the_step_gives_way_at_the_next_heartbeat(tmp_path, bus):
    cfg, stop, learner, actor, th, method = _live_run(tmp_path, bus, actor=ActorConfig(max_version_step=1000))
    wait_for(lambda: actor.params is not None and actor._vouched is not None, timeout=30)
    forged = learner.version + 900                # inside the bound: adopted for now ...
    bus.publish(keys.params(cfg.run_id), _forged_params(cfg, learner, method, forged))
    wait_for(lambda: actor.params["version"] == forged)
    wait_for(lambda: actor.params["version"] < forged, timeout=30)   # ... and dropped once a heartbeat disagrees
    assert learner.version < forged and actor.params_fenced == 0
    stop.set()
    th.join(5)
