"""The pipelined actor (two env groups alternating at the shield) and shield
shards (actor i asks shard i % shields): same chunks, same versions, only
shielded actions executed, every shard serving its own actors."""
import sys
import threading
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).parent))
from services_fakes import FakeBatchEnv, FakeMethod, fake_propose, fake_solve  # noqa: E402
from test_services import make_cfg, wait_for  # noqa: E402

from common import keys, wire  # noqa: E402
from common.transport import Bus  # noqa: E402
from services.actor.service import ActorService  # noqa: E402
from services.config import ActorConfig, PortsConfig, TrainConfig  # noqa: E402
from deploy.threads import run_inprocess  # noqa: E402
from services.launcher import entry_argv, run_members  # noqa: E402
from services.shield.service import ShieldService  # noqa: E402


def _groups(seed=0):
    return [FakeBatchEnv(2, seed=seed), FakeBatchEnv(1, seed=seed + 100)]


def test_pipelined_inprocess_run_batches_both_groups_and_shields_every_action(tmp_path):
    cfg = make_cfg(tmp_path, envs_per_actor=3)
    envs = [_groups(0), _groups(1)]
    method = FakeMethod()
    out = run_inprocess(cfg, progress=False, method=method, envs=envs, propose=fake_propose,
                        solve=fake_solve, timeout_s=60)
    assert out["updates"] == 3 and out["rejected"] == {}
    for b in method.batches:   # 2 actors x (2 + 1) envs side by side, chunk_len 6
        assert b["obs"].shape == (6, 6, 3, 5) and b["a_exec"].shape == (6, 6, 9)
        assert (b["a_exec"][..., 0] >= 0.5 - 1e-12).all() and (b["a_prop"][..., 0] < 0.5).any()
    for groups in envs:
        n0, n1 = (len(g.executed) for g in groups)
        assert n0 and abs(n0 - n1) <= 1      # the groups alternate, one step each per cycle
        assert all((a[:, 0] >= 0.5 - 1e-12).all() for g in groups for a in g.executed)


def test_pipelined_chunks_carry_each_steps_version(tmp_path):
    """Parameters that change mid-chunk: every step's version is the one both
    groups proposed with; the chunk's version is its oldest."""
    cfg = make_cfg(tmp_path, chunk_len=8, actors=1, envs_per_actor=3, actor=ActorConfig(max_chunks_ahead=100))
    bus, stop = Bus.open(inprocess=True), threading.Event()
    chunks = []
    bus.subscribe(keys.traj_all(cfg.run_id), lambda _k, p: chunks.append(wire.decode(p, run_id=cfg.run_id).body))
    threading.Thread(target=ShieldService(cfg, bus, stop=stop, solve=fake_solve).run, daemon=True).start()
    groups = _groups()
    actor = ActorService(cfg, bus, 0, stop=stop, env=groups, propose=fake_propose)
    assert actor.pipelined
    threading.Thread(target=actor.run, daemon=True).start()
    wait_for(lambda: actor.state == "waiting")   # subscribed to parameters
    m = FakeMethod()
    try:
        for version in range(4):
            body = {"version": version, "incarnation": "inc", "method": cfg.method, "params": m.policy_params(),
                    "settings": {"kappa": 1.0}}
            bus.publish(keys.params(cfg.run_id), wire.encode("params", body, run_id=cfg.run_id,
                                                             sender="learner/0", seq=version))
            wait_for(lambda: actor.env_steps >= 3 * 5 * (version + 1), timeout=20)
        wait_for(lambda: len(chunks) >= 2, timeout=20)
    finally:
        stop.set()
        bus.close()
    seen = set()
    for c in chunks:
        v = np.asarray(c["version_t"])
        assert v.shape == (8,) and (np.diff(v) >= 0).all() and c["version"] == v.min()
        assert c["obs"].shape[1] == 3 and (np.asarray(c["shield_status"]) == 0).all()
        seen |= set(v.tolist())
    assert len(seen) >= 2          # a chunk spanned a parameter change, per-step versions kept it
    n0, n1 = (len(g.executed) for g in groups)
    assert abs(n0 - n1) <= 1


class _CountingBus:
    """The actor's bus, counting shield queries sent whose replies nobody has
    started reading yet."""

    def __init__(self, bus):
        self.bus, self.outstanding = bus, 0

    def __getattr__(self, name):
        return getattr(self.bus, name)

    def replies(self, key, payload, timeout):
        self.outstanding += 1
        it = self.bus.replies(key, payload, timeout)

        def read():
            self.outstanding -= 1
            yield from it
        return read()


class _WatchedEnv(FakeBatchEnv):
    def __init__(self, n, seed, bus):
        super().__init__(n, seed=seed)
        self.bus, self.out_at_step = bus, []

    def step(self, actions):
        self.out_at_step.append(self.bus.outstanding)
        return super().step(actions)


@pytest.mark.parametrize("pipeline", [False, True], ids=["sync", "pipelined"])
def test_a_pipelined_group_steps_while_the_other_groups_query_is_out(tmp_path, pipeline):
    """Double buffering, not just two groups in turn: inside a chunk, every
    group steps physics while exactly one query (the other group's) is at the
    shield; at a chunk's last step group 1 steps with none out (the pipeline
    empties there). The synchronous actor never has a query out while stepping."""
    T = 4
    cfg = make_cfg(tmp_path, chunk_len=T, actors=1, envs_per_actor=3,
                   actor=ActorConfig(max_chunks_ahead=100, pipeline=pipeline))
    bus, stop = Bus.open(inprocess=True), threading.Event()
    threading.Thread(target=ShieldService(cfg, bus, stop=stop, solve=fake_solve).run, daemon=True).start()
    counting = _CountingBus(bus)
    groups = [_WatchedEnv(2, 0, counting), _WatchedEnv(1, 1, counting)] if pipeline else [_WatchedEnv(3, 0, counting)]
    actor = ActorService(cfg, counting, 0, stop=stop, env=groups if pipeline else groups[0], propose=fake_propose)
    threading.Thread(target=actor.run, daemon=True).start()
    wait_for(lambda: actor.state == "waiting")
    body = {"version": 0, "incarnation": "inc", "method": cfg.method, "params": FakeMethod().policy_params(),
            "settings": {"kappa": 1.0}}
    bus.publish(keys.params(cfg.run_id), wire.encode("params", body, run_id=cfg.run_id, sender="learner/0", seq=0))
    try:
        wait_for(lambda: len(groups[-1].out_at_step) >= 3 * T, timeout=20)
    finally:
        stop.set()
        bus.close()
    n = 3 * T
    if not pipeline:
        assert groups[0].out_at_step[:n] == [0] * n
        return
    assert groups[0].out_at_step[:n] == [1] * n                      # group 1's query is out
    assert groups[1].out_at_step[:n] == ([1] * (T - 1) + [0]) * 3    # group 0's next one, but at chunk ends
    assert all((a[:, 0] >= 0.5 - 1e-12).all() for g in groups for a in g.executed)


def test_unshielded_or_single_env_actors_do_not_pipeline(tmp_path):
    cfg = make_cfg(tmp_path, method="happo")
    assert not ActorService(cfg, Bus.open(inprocess=True), 0).pipelined
    one = make_cfg(tmp_path, envs_per_actor=1)
    assert not ActorService(one, Bus.open(inprocess=True), 0).pipelined
    two = ActorService(make_cfg(tmp_path, envs_per_actor=5, actor=ActorConfig(pipeline=True)), Bus.open(inprocess=True), 0)
    assert two.pipelined and [e.K for e in two._make_envs()] == [3, 2]


def test_shards_bind_actors_by_id_and_each_serves_its_own(tmp_path):
    cfg = make_cfg(tmp_path, actors=3, shields=2)
    assert [cfg.shield_shard(i) for i in range(3)] == [0, 1, 0]
    assert [cfg.actors_of_shard(k) for k in range(2)] == [2, 1]
    assert keys.shield(cfg.run_id, 1) == "sage/t1/shield/1"
    members = run_members(range(3), shields=2)
    assert [m.name for m in members] == ["shield", "shield-1", "learner", "actor-0", "actor-1", "actor-2"]
    assert entry_argv(members[1], "RUN.json", "py")[-2:] == ["--shard", "1"]
    envs = [FakeBatchEnv(2, seed=i) for i in range(3)]
    out = run_inprocess(cfg, progress=False, method=FakeMethod(), envs=envs, propose=fake_propose,
                        solve=fake_solve, timeout_s=60)
    assert out["updates"] == 3
    rows = [sh["rows"] for sh in out["shields"]]
    # shard 0 answered actors 0 and 2, shard 1 actor 1: every executed step went through its
    # shard (plus at most one answered query per actor that the stop left unexecuted)
    executed = [len(e.executed) * 2 for e in envs]
    assert 0 <= rows[0] - executed[0] - executed[2] <= 2 * 2
    assert 0 <= rows[1] - executed[1] <= 2 and executed[1] > 0


@pytest.mark.parametrize("bad, why", [(dict(actors=1, shields=2), "shields"),
                                      (dict(actors=20, shields=12, ports=PortsConfig(shield=9401, actor_base=9410)),
                                       "overlap")])
def test_bad_shard_counts_are_refused(tmp_path, bad, why):
    with pytest.raises(ValueError, match=why):
        TrainConfig(run_id="t", **bad).validate()
