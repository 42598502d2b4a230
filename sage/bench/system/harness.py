"""What every benchmark of ``sage bench system`` shares: run configs,
supervised processes (started, checked, CPU-probed, stopped), the shield
requests the round trips send, the learner used to publish parameters, and
the physics bound."""
from __future__ import annotations

import os
import sys
import time
from pathlib import Path

import numpy as np

from common import keys, wire
from common.env.batch_env import BatchEnv
from common.safety_rows import SafetyRows
from common.shield.prune import drop_box_redundant_rows
from common.spec import JOINT_ACT_DIM
from deploy.supervisor import Supervisor, SupervisorConfig
from sage.bench.env import bench_env
from sage.bench.system.config import SystemBenchConfig
from sage.bench.system.cpu import process_cpu_s
from sage.bench.system.meter import Repeater
from services.config import ActorConfig, TrainConfig
from services.learner.service import LearnerService, build_method


class ParamsOnlyLearner(LearnerService):
    """The learner's parameter message without its backlog: nothing consumes the
    bench's chunks, so a backlog would report them all unsettled and pace the
    actors (``ActorConfig.max_chunks_ahead``); without one the actor paces on
    versions alone."""

    def backlog(self) -> dict:
        return {}


class Harness:
    """The config, the log and the supervisors of one bench run."""

    def __init__(self, cfg: SystemBenchConfig, work_dir: Path, log=None):
        self.cfg = cfg.validate()
        self.work = Path(work_dir)
        self.log = log or (lambda text: print(text, file=sys.stderr, flush=True))
        self._n = 0
        self._sups: list = []

    def train_config(self, actors: int, connect: list[str] | None, tag: str, unpaced: bool = False,
                     method: str | None = None, shields: int = 1, learner_defaults: bool = False):
        """A run config for one phase; one chunk per update, so the learner's
        batch does not depend on how many actors are up yet. ``unpaced``: the
        actor never waits for the learner (phase 1 has none: it measures the
        actor's own stepping rate)."""
        self._n += 1
        run_id = f"bench-{tag}-{os.getpid()}-{self._n}"
        cfg = TrainConfig(run_id=run_id, run_dir=str(self.work / run_id), scenario=self.cfg.scenario,
                          method=method or self.cfg.method, actors=actors, shields=shields,
                          envs_per_actor=self.cfg.envs_per_actor,
                          chunk_len=self.cfg.chunk_len, chunks_per_update=1, updates=1_000_000,
                          status_period_s=0.2, eval_episodes=0, checkpoint_every=1_000_000, seed=self.cfg.seed,
                          deploy_probe_every=0,   # a probe would pause the learner mid-measurement
                          mode="supervised",
                          # the whole-system phases train with the method's defaults (what a run costs);
                          # the shield/actor phases have no learner
                          algo={} if learner_defaults else {"epochs": 1, "minibatches": 1})
        if connect:
            cfg.transport.connect, cfg.transport.mode = list(connect), "client"
        cfg.actor.exit_on_unhealthy = True
        if unpaced:   # the most the config allows; the feeder's new versions keep it from binding
            cfg.actor.max_chunks_ahead = ActorConfig.__dataclass_fields__["max_chunks_ahead"].metadata["range"][2]
        cfg.resolve()
        return cfg, cfg.save(Path(cfg.run_dir) / "config.json")

    # ------------------------------------------------------------- supervised processes
    def supervise(self, specs, run_dir, restart_budget: int = 0):
        """Start ``specs`` under a supervisor. By default a crash fails the
        benchmark; with a ``restart_budget`` crashed services are restarted
        and counted (``restarts`` in the result) instead."""
        cfg = SupervisorConfig(restart_budget=restart_budget, backoff_initial_s=0.2, term_deadline_s=10.0)
        sup = Supervisor(specs, run_dir, cfg, out=sys.stderr)
        self._sups.append(sup)
        sup.start()
        return sup

    def check(self) -> None:
        for sup in self._sups:
            if sup.poll() is not None or any(c.state in ("failed", "done") for c in sup.children):
                bad = {c.spec.name: (c.state, c.last_code) for c in sup.children if c.state != "running"}
                raise RuntimeError(f"a service exited during the benchmark: {bad}; logs in {sup.log_dir}")

    def cpu_probe(self) -> dict[str, float]:
        """CPU seconds so far of every running supervised service, by service name."""
        out = {}
        for sup in self._sups:
            for c in sup.children:
                if c.proc is not None and c.proc.poll() is None:
                    used = process_cpu_s(c.proc.pid)
                    if used is not None:
                        out[c.spec.name] = used
        return out

    def restarts(self) -> dict[str, int]:
        return {c.spec.name: c.starts - 1 for sup in self._sups for c in sup.children if c.starts > 1}

    def stop(self, sup) -> None:
        sup.shutdown("bench done")
        self._sups.remove(sup)

    def stop_all(self) -> None:
        for sup in reversed(list(self._sups)):
            self.stop(sup)

    # ------------------------------------------------------------- what the measurements send
    def requests(self) -> dict[int, dict]:
        """Shield problems per batch size: the scenario's real safety rows at
        reset of ``max(batch_sizes)`` envs, random proposals in the action box."""
        n = max(self.cfg.batch_sizes)
        out = BatchEnv(TrainConfig(scenario=self.cfg.scenario).env_config(), n, seed=self.cfg.seed).reset()
        full = {"a_prop": np.random.default_rng(self.cfg.seed).uniform(-1, 1, size=(n, JOINT_ACT_DIM)),
                **SafetyRows.of(out).as_dict()}
        return {B: {k: np.ascontiguousarray(v[:B]) for k, v in full.items()} for B in self.cfg.batch_sizes}

    @staticmethod
    def pruned(batches: dict[int, dict]) -> dict[int, dict]:
        """The same requests as an actor sends them (``actor.prune_rows``)."""
        return {B: {"a_prop": b["a_prop"], **drop_box_redundant_rows(b["a_prop"], SafetyRows.of(b)).as_dict()}
                for B, b in batches.items()}

    @staticmethod
    def params_publisher(cfg, bus):
        """The real learner service object, used only for ``publish_params``."""
        learner = ParamsOnlyLearner(cfg, bus, 0)
        learner.method = build_method(cfg)
        return learner

    @staticmethod
    def feed_params(learner, period_s: float = 0.5) -> Repeater:
        """A new parameter version every ``period_s`` until stopped, so the unpaced
        actors never wait: each version resets their count of chunks ahead."""
        def publish_next():
            learner.version += 1
            learner.publish_params()
        return Repeater(publish_next, period_s)

    def _wait_shield(self, bus, run_id: str, alive) -> None:
        """Until the shield answers a trivial request (its queryable is declared)."""
        body = {"a_prop": np.zeros((1, JOINT_ACT_DIM)), "C": np.zeros((1, 1, JOINT_ACT_DIM)), "c": np.zeros((1, 1)),
                "row_mask": np.zeros((1, 1), bool), "fixed_mask": np.zeros((1, JOINT_ACT_DIM), bool)}
        payload = wire.encode("shield_req", body, run_id=run_id, sender="cli/bench", seq=0)
        deadline = time.monotonic() + self.cfg.start_timeout_s
        while True:
            reply = bus.request(keys.shield(run_id), payload, timeout=1.0)
            if reply is not None and reply.ok is not None:
                return
            alive()
            if time.monotonic() > deadline:
                raise TimeoutError(f"the shield never answered within {self.cfg.start_timeout_s} s")
            time.sleep(0.05)

    def measure_physics_bound(self) -> float:
        """The one-core raw physics bound of the actors' batch (``sage bench env``'s
        ``raw_physics_env_steps_per_s``), measured now."""
        raw = bench_env(self.cfg.scenario, num_envs=self.cfg.envs_per_actor, steps=50, seed=self.cfg.seed)
        return float(raw["raw_physics_env_steps_per_s"])
