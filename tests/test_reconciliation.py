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

import os
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest
import zenoh
from prometheus_client import CollectorRegistry

sys.path.insert(0, str(Path(__file__).parent))
from services_fakes import FakeBatchEnv, FakeMethod, fake_propose, fake_solve  # noqa: E402
from conftest import wait_for  # noqa: E402
from test_services import make_cfg  # noqa: E402

from common.transport import Bus  # noqa: E402
from deploy.driver import free_tcp_port, wait_tcp_ready  # noqa: E402
from services.actor.service import ActorService  # noqa: E402
from services.config import ActorConfig  # noqa: E402
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


# ~3 min on the 2-core host: the services share one interpreter, and ~210 chunks/s
# under churn is what its lock lets through; CHURN_CHUNKS=100000 runs the 10^5
CHURN_CHUNKS = int(os.environ.get("CHURN_CHUNKS", 40_000))
CHURN_BUDGET_S = CHURN_CHUNKS / 100   # seconds, at half that rate
ROUTER_PERIOD_S = 1.5    # the router is killed (SIGKILL) and started again on its port this often
LEARNER_PERIOD_S = 5.0   # each learner runs this long, then the next resumes its checkpoint
ROOT = Path(__file__).resolve().parents[1]


class SteadyMethod(FakeMethod):
    """FakeMethod for long runs: weights that stay put (FakeMethod's shrink by 0.9
    per update reaches a float32 zero row, which actors refuse, within ~500
    updates) and no batches kept."""

    def update(self, batch, progress):
        self.n += 1
        return {"policy_loss": float(batch["reward"].mean()), "n": float(self.n)}


class Router:
    """``deploy.router`` as a process on one port, killed and started again there."""

    def __init__(self):
        self.port = free_tcp_port()
        self.endpoint = f"tcp/127.0.0.1:{self.port}"
        self.restarts = 0
        self.proc = self._start()

    def _start(self) -> subprocess.Popen:
        proc = subprocess.Popen([sys.executable, "-m", "deploy.router", "--listen", self.endpoint], cwd=ROOT,
                                stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        assert wait_tcp_ready("127.0.0.1", self.port, 30, give_up=lambda: proc.poll() is not None), \
            f"no router on {self.endpoint} (exit {proc.poll()})"
        return proc

    def restart(self) -> None:
        self.kill()   # SIGKILL: the clients get no goodbye, their links just break
        self.proc = self._start()
        self.restarts += 1

    def kill(self) -> None:
        self.proc.kill()
        self.proc.wait()

    def client(self, timeout: float = 30.0) -> Bus:
        """A client session, as a supervised service opens one; retried while the router
        is between two lives (a Zenoh client does not open without its router)."""
        deadline = time.monotonic() + timeout
        while True:
            try:
                return Bus.open(connect=[self.endpoint], mode="client")
            except zenoh.ZError:
                if time.monotonic() > deadline:
                    raise
                time.sleep(0.05)


@pytest.mark.slow
def test_a_client_hears_again_soon_after_its_router_restarts():
    """Zenoh's default redial (1 s, doubling to 4 s) left every service deaf that
    long after a router restart; common/transport.py's CONNECT_RETRY shortens it."""
    router = Router()
    pub, sub = router.client(), router.client()
    got: list[bytes] = []
    sub.subscribe("churn/test", lambda _k, p: got.append(p))

    def heard_after(t0: float, timeout: float = 10.0) -> float:
        got.clear()
        while not got and time.monotonic() - t0 < timeout:
            pub.publish("churn/test", b"x")
            time.sleep(0.01)
        assert got, f"nothing heard {timeout} s after the router was killed"
        return time.monotonic() - t0

    try:
        heard_after(time.monotonic())
        deaf = []   # seconds from the kill until a publication arrives again (the router takes ~0.1 s to start)
        for _ in range(3):
            t_kill = time.monotonic()
            router.restart()
            deaf.append(heard_after(t_kill))
        print({"deaf_s": [round(d, 3) for d in deaf]})
        assert max(deaf) < 0.7, deaf
    finally:
        pub.close()
        sub.close()
        router.kill()


@pytest.mark.slow
@pytest.mark.timeout(CHURN_BUDGET_S + 120)
def test_every_chunk_is_accounted_for_across_router_and_learner_restarts(tmp_path):
    """The services as threads on their own client sessions to a router process
    that is killed every ROUTER_PERIOD_S, the learner resumed from its checkpoint
    every LEARNER_PERIOD_S, until the actors sent CHURN_CHUNKS chunks; then the
    identity of the in-process test, exactly. One step per chunk and one env per
    actor make chunks cheap; 32-chunk batches keep the learner's per-update work
    (metrics rows, checkpoint, parameter broadcast) from pacing the actors."""
    cfg = make_cfg(tmp_path, updates=10**6, chunk_len=1, envs_per_actor=1, chunks_per_update=32,
                   learner_queue_chunks=128, checkpoint_every=1, deploy_probe_every=0, tensorboard=False,
                   actor=ActorConfig(max_chunks_ahead=24))
    router = Router()
    stop_actors, stop_shield, stop_churn = threading.Event(), threading.Event(), threading.Event()
    buses: list[Bus] = []
    churn_errors: list[BaseException] = []

    def churn():
        try:
            while not stop_churn.wait(ROUTER_PERIOD_S):
                router.restart()
        except BaseException as exc:   # noqa: BLE001 - re-raised by the test thread
            churn_errors.append(exc)

    def client() -> Bus:
        buses.append(router.client())
        return buses[-1]

    churner = threading.Thread(target=churn, daemon=True)

    try:
        shield = ShieldService(cfg, client(), stop=stop_shield, solve=fake_solve)
        threading.Thread(target=shield.run, daemon=True).start()
        actors = [ActorService(cfg, client(), i, stop=stop_actors, env=FakeBatchEnv(1, seed=i),
                               propose=fake_propose) for i in range(cfg.actors)]
        actor_threads = [threading.Thread(target=a.run, daemon=True) for a in actors]
        for th in actor_threads:
            th.start()
        sent = lambda: sum(a.chunks_sent for a in actors)   # noqa: E731
        t0 = time.monotonic()
        churner.start()
        learner_restarts, lost_while_learning = -1, 0
        while True:   # each learner resumes the previous one's checkpoint
            own, bus = threading.Event(), client()
            learner = LearnerService(cfg, bus, 0, CollectorRegistry(), own, method=SteadyMethod())
            th = threading.Thread(target=learner.run, daemon=True)
            th.start()
            learner_restarts += 1
            wait_for(lambda: learner.state == "running", 30)
            resumed = {f"actor/{a.actor_id}": learner.last_seq.get(f"actor/{a.actor_id}", -1) for a in actors}
            t_end, lost_at_first = time.monotonic() + LEARNER_PERIOD_S, None
            while time.monotonic() < t_end and sent() < CHURN_CHUNKS:
                assert not churn_errors, churn_errors
                assert time.monotonic() - t0 < CHURN_BUDGET_S, f"{sent()} of {CHURN_CHUNKS} chunks in the budget"
                if lost_at_first is None and all(learner.last_seq.get(k, -1) > v for k, v in resumed.items()):
                    # the gap of this learner's start is counted: from here on, gaps are chunks
                    # the router's restarts (or the full inbox) lost while it was learning
                    lost_at_first = learner.counts["lost"] - learner.counts["queue_full"]
                time.sleep(0.01)
            if lost_at_first is not None:
                lost_while_learning += learner.counts["lost"] - learner.counts["queue_full"] - lost_at_first
            if sent() >= CHURN_CHUNKS:
                break
            own.set()   # stop (the final checkpoint is written); chunks go on meanwhile
            th.join(30)
            assert not th.is_alive()
            bus.close()   # as its process would: an open session goes on receiving every chunk
        stop_churn.set()
        churner.join(30)
        assert not churn_errors, churn_errors
        # the router stays up from here: the actors stop, their last chunks reach the last learner
        stop_actors.set()
        for a_th in actor_threads:
            a_th.join(30)
            assert not a_th.is_alive()
        try:
            wait_for(lambda: all(learner.last_seq.get(f"actor/{a.actor_id}", -1) + 1 == a.chunks_sent
                                 for a in actors), 10)
        except AssertionError:
            pass   # a last chunk lost on its way: after the finish, bounded below
        own.set()
        th.join(30)
        wall_s = time.monotonic() - t0
        c = learner.counts
        accounted = {s: n + 1 for s, n in learner.last_seq.items()}
        print({"chunks_sent": sent(), "router_restarts": router.restarts, "learner_restarts": learner_restarts,
               "wall_s": round(wall_s, 1), "lost_while_learning": lost_while_learning,
               "pending": len(learner.pending), **c,
               "shield_failures": [a.shield_failures for a in actors]})
        assert sent() >= CHURN_CHUNKS
        assert sum(c.get(k, 0) for k in IN_SEQUENCE) + len(learner.pending) == sum(accounted.values()), (c, accounted)
        assert c["duplicate"] == c["seq_jump"] == c["actor_restarts"] == 0
        # the restarts cost chunks, all counted; the router's too (gaps while a learner ran)
        assert lost_while_learning > 0 and c["incarnation"] + c["unused_restart"] > 0
        assert all(a.shield_failures > 0 for a in actors)   # the outages reached them, and they went on
        for a in actors:
            after_finish = a.chunks_sent - accounted.get(f"actor/{a.actor_id}", 0)
            assert 0 <= after_finish <= 2, (a.actor_id, a.chunks_sent, accounted)
    finally:
        stop_churn.set()
        if churner.is_alive():
            churner.join(30)   # before the last kill: no router may outlive the test
        stop_actors.set()
        stop_shield.set()
        time.sleep(0.2)
        for b in buses:
            b.close()
        router.kill()
