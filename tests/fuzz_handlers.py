"""Coverage-guided fuzzing (atheris) of each service's message handler, not
only the decoder (issue 32): the shield's request path (decode with the run's
bounds, per-sender FIFOs, fair batch, solve with the real QP, reply), the
actor's parameter and heartbeat handlers and its check of a shield answer,
and the learner's chunk path (inbox, decode, sequence accounting, admission,
update). Whatever the bytes, no handler raises; every input is answered,
admitted or counted.

    python tests/fuzz_handlers.py -runs=2000 -max_total_time=60 CORPUS_DIR
    python tests/fuzz_handlers.py --write-corpus CORPUS_DIR   # seeds from real messages

Input: the first byte picks the handler, the rest is the payload. Run by
tests/test_fuzz_handlers.py (bounded in runs and time) when atheris is installed.
"""
from __future__ import annotations

import logging
import sys
import threading
import time
from pathlib import Path

import atheris

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

# compiled (numba) modules first, uninstrumented: instrumented bytecode is not numba's to compile
import common.algos.methods  # noqa: E402,F401
import common.env.batch_env  # noqa: E402,F401
import common.evaluation.deployment  # noqa: E402,F401
import common.policy.rollout  # noqa: E402,F401
import common.shield.prune  # noqa: E402,F401
import common.shield.qp  # noqa: E402,F401
import common.shield.row_kernels  # noqa: E402,F401

with atheris.instrument_imports():
    import numpy as np
    from prometheus_client import CollectorRegistry

    from common import keys, wire
    from common.safety_rows import SafetyRows
    from common.shield.verify import verify_answer
    from services.actor.service import ActorService
    from services.config import ActorConfig, TrainConfig
    from services.learner.service import LearnerService
    from services.shield.service import ShieldService
    from services_fakes import FakeBatchEnv, FakeMethod

RUN = "fuzz"
logging.disable(logging.CRITICAL)   # handlers log refusals; millions of lines help nobody


class FakeRequest:
    """A Zenoh query stand-in: records the one reply or error it gets."""

    def __init__(self, payload: bytes):
        self.payload, self.t_recv, self.answered = payload, time.perf_counter(), 0

    def reply(self, payload: bytes) -> None:
        self.answered += 1

    def reply_err(self, payload: bytes) -> None:
        self.answered += 1

    def finish(self) -> None:
        pass


def _cfg(tmp: str) -> TrainConfig:
    return TrainConfig(run_id=RUN, run_dir=tmp, actors=2, envs_per_actor=2, chunk_len=2, deploy_probe_every=0,
                       checkpoint_every=10**6, actor=ActorConfig(shield_timeout_s=60.0)).validate()


def _services(tmp: str):
    cfg = _cfg(tmp)
    shield = ShieldService(cfg, None, registry=CollectorRegistry(), stop=threading.Event())
    actor = ActorService(cfg, None, 0, CollectorRegistry(), threading.Event(), env=FakeBatchEnv(2))
    learner = LearnerService(cfg, None, 0, CollectorRegistry(), threading.Event(), method=FakeMethod())
    learner.version = 3
    learner.incarnation = "LEARNER"   # the seed chunk's incarnation: seeds are admitted, mutants may not be
    return cfg, shield, actor, learner


def seeds() -> dict[str, bytes]:
    """Real messages of every kind the handlers take, each with its handler byte."""
    env = FakeBatchEnv(2)
    out = env.reset()
    rows = SafetyRows.of(out)
    a = np.random.default_rng(0).uniform(-1, 1, (2, 9))
    req = wire.encode("shield_req", {"a_prop": a, **rows.as_dict()}, run_id=RUN, sender="actor/0", seq=0)
    from services_fakes import fake_solve

    res = fake_solve(a, rows)
    rep = wire.encode("shield_rep", {"a_exec": res.a_exec, "status": np.zeros(2, np.int32), "correction_norm": np.zeros(2),
                                     "slack": np.zeros(2), "batch_size": 2, "solve_s": 0.0}, run_id=RUN, sender="shield/0", seq=0)
    params = wire.encode("params", {"version": 3, "incarnation": "inc", "method": "sage", "params": FakeMethod().policy_params(),
                                    "settings": {"kappa": 1.0}}, run_id=RUN, sender="learner/0", seq=0)
    status = wire.encode("status", {"role": "learner", "id": "0", "state": "running", "pid": 1, "uptime_s": 1.0, "version": 3,
                                    "env_steps": 0, "env_steps_per_s": 0.0, "updates": 0, "success_rate": None,
                                    "shield_p99_s": None, "message": "", "extra": {}}, run_id=RUN, sender="learner/0", seq=0)
    T, K = 2, 2
    nxt = env.step(res.a_exec)
    step = {"obs": out["obs"], "state": out["state"], "C": out["C"], "c": out["c"], "row_mask": out["row_mask"],
            "fixed_mask": out["fixed_mask"], "a_st": a, "a_bar": a, "a_prop": a, "a_exec": res.a_exec,
            "shield_status": np.zeros(K, np.int32), "logp": np.zeros((K, 3)), "leaf": np.zeros((K, 3), np.int64),
            "reward": nxt["reward"], "terminated": nxt["terminated"], "truncated": nxt["truncated"],
            "final_state": nxt["final_state"], "final_obs": nxt["final_obs"]}
    body = {k: np.stack([np.asarray(step[k])] * T) for k in wire.TRAJ_STEP_FIELDS}
    body.update(actor_id=0, version=3, incarnation="LEARNER", env_steps=T * K, version_t=np.full(T, 3, np.int64),
                last_state=out["state"], last_obs=out["obs"], episodes=[{"success": 1.0}])
    traj = wire.encode("traj", body, run_id=RUN, sender="actor/0", seq=0)
    return {"shield_req": b"\x00" + req, "params": b"\x01" + params, "status": b"\x02" + status,
            "shield_rep": b"\x03" + rep, "traj": b"\x04" + traj}


STATE: dict = {}


def test_one_input(data: bytes) -> None:
    if len(data) < 1:
        return
    cfg, shield, actor, learner = STATE["services"]
    target, payload = data[0] % 5, bytes(data[1:])
    if target == 0:                       # shield: decode, FIFO, fair batch, solve, reply
        req = FakeRequest(payload)
        shield._admit(req)
        good = shield._fair_batch()
        shield.handle([r for r, _ in good], good)
        assert req.answered <= 1
        assert not shield._pending and shield._pending_rows == 0
    elif target == 1:                     # actor: parameters
        actor._on_params(keys.params(RUN), payload)
        with actor._lock:
            actor._pending = None         # each input judged against the same held state
    elif target == 2:                     # actor: the learner's heartbeat
        actor._on_learner_status(keys.status(RUN, "learner", 0), payload)
    elif target == 3:                     # actor: the check of a shield answer
        msg = actor.decode(payload, "shield_rep")
        if msg is not None:
            verdict = verify_answer(STATE["a_prop"], STATE["rows"], msg.body["a_exec"], msg.body["status"])
            assert verdict is None or isinstance(verdict, str)
    else:                                 # learner: inbox, decode, accounting, admission, update
        learner._on_traj(keys.traj(RUN, 0), payload)
        learner.drain()
        learner.try_update()
        learner.pending.clear()


def main() -> None:
    if len(sys.argv) == 3 and sys.argv[1] == "--write-corpus":
        d = Path(sys.argv[2])
        d.mkdir(parents=True, exist_ok=True)
        for name, blob in seeds().items():
            (d / name).write_bytes(blob)
        return
    import tempfile

    tmp = tempfile.mkdtemp(prefix="sage-fuzz-")
    STATE["services"] = _services(tmp)
    env = FakeBatchEnv(2)
    STATE["rows"] = SafetyRows.of(env.reset())
    STATE["a_prop"] = np.random.default_rng(0).uniform(-1, 1, (2, 9))
    atheris.Setup(sys.argv, test_one_input)
    atheris.Fuzz()


if __name__ == "__main__":
    main()
