"""Actor service: K environments, newest parameters, one batched shield query
per step (per env group), trajectory chunks every ``chunk_len`` steps.

Per step (Eq. action_chain): ``common.policy.rollout.propose`` gives a_ST, the
proposal center a_bar (SAIL map with the learner's kappa in SAIL methods,
identity otherwise) and a sampled a_prop with its behavior log-prob; shielded
methods send all K rows in ONE query and execute the shield's a_exec,
unshielded HAPPO executes a_prop. Fail closed: without a shield answer
nothing is executed; the step is retried, counted, and after
``actor.unhealthy_after_s`` the actor reports itself unhealthy (status,
metric, log) and, if configured, exits with code 3.

Pipelining (``actor.pipeline``, Sample Factory's double-buffered sampling):
the K envs are two groups that alternate. Each group, right after it steps
physics, proposes its next step and sends that query, so group 0's query is
at the shield while group 1 waits, steps and proposes, and the other way
round (a Zenoh get returns at once; its replies queue up). Both groups'
proposals of one step use the same parameters (adopted once, after group 0
stepped); chunk ends and learner restarts empty the pipeline. No threads: the
only concurrency is the shield's and the network's. The step's chunk record
is the two groups side by side (group 0's envs first), so the learner sees
the same chunks.
"""
from __future__ import annotations

import os
import threading
import time
from collections import defaultdict, deque

import numpy as np

from common import keys, wire
from common.algos.registry import method_spec
from common.env.batch_env import BatchEnv
from common.metrics_prom import Window
from common.policy.rollout import propose as default_propose
from common.policy.tree import InvalidParams, ValidatedParams
from common.safety_rows import SafetyRows
from common.shield.prune import drop_box_redundant_rows
from common.shield.verify import verify_answer
from common.spec import CARRIER_ACT_DIM, N_CARRIERS
from services.base import RateMeter, Service

EXIT_UNHEALTHY = 3
EXIT_CHAOS = 86    # actor.chaos_crash_prob fired (fault injection)
UNSHIELDED = -1   # shield_status of a step an unshielded method executed as proposed

TRAJ = wire.SCHEMAS["traj"]   # the chunk layout (docs/wire.md): fields, shapes, the dtypes we send


class ActorUnhealthy(RuntimeError):
    pass


class ActorService(Service):
    role = "actor"

    def __init__(self, cfg, bus, member_id=0, registry=None, stop=None, env=None, propose=None):
        super().__init__(cfg, bus, member_id, registry, stop)
        self.actor_id = int(member_id)
        # one env, or the env groups of a pipelined actor (tests inject either)
        self.envs = None if env is None else list(env) if isinstance(env, (list, tuple)) else [env]
        self._propose = propose if propose is not None else default_propose
        spec = method_spec(cfg.method)
        self.shielded, self.uses_sail = spec.shielded, spec.uses_sail
        self.shield_key = keys.shield(cfg.run_id, cfg.shield_shard(self.actor_id))
        self.pipelined = (cfg.actor.pipeline and self.shielded and cfg.envs_per_actor >= 2
                          if self.envs is None else len(self.envs) > 1)
        self.rng = np.random.default_rng([cfg.seed, 1000 + self.actor_id])
        # parameters: written by the subscriber thread, adopted by the loop
        self._lock = threading.Lock()
        self._pending: dict | None = None
        self.params: dict | None = None
        self.env_steps = 0
        self.steps_rate = RateMeter()
        self.rtt = Window()
        self.recent_success: deque[float] = deque(maxlen=100)
        self.shield_failures = 0
        self.answers_refused: dict[str, int] = defaultdict(int)   # reason -> shield answers not executed
        self.chunks_sent = 0
        self.params_refused = 0
        self.params_fenced = 0      # of those: version jumps no learner heartbeat vouches for
        self._vouched: int | None = None   # the learner's newest heartbeat version (None: none heard yet)
        self.chunks_discarded = 0   # partial chunks dropped on a learner restart (and their env steps)
        self.steps_discarded = 0
        self._chaos = (np.random.default_rng([cfg.seed, 2000 + self.actor_id, os.getpid()])
                       if cfg.actor.chaos_crash_prob > 0 else None)
        self.obs_dim: int | None = self.envs[0].obs_dim if self.envs else None   # set with the envs in run()
        self._sent_chunks: deque[tuple[int, str, int]] = deque(maxlen=16)   # (newest version, incarnation, seq)
        self.steps_taken = 0   # batched steps (each K env steps)
        self.shield_wait_s = 0.0   # rollout loop blocked on shield answers
        self.loop_cpu_s = 0.0      # the rollout loop thread's CPU time

    # ------------------------------------------------------------- parameters
    def _on_params(self, _key: str, payload: bytes) -> None:
        msg = self.decode(payload, "params")
        if msg is None:
            return
        b = msg.body
        with self._lock:
            fenced = self._fence(b)
        if fenced:
            self.params_fenced += 1
        refused = fenced or self._check_params(b)
        if refused:
            self.params_refused += 1
            self.m.params_rejected.labels(**self.labels).inc()
            if self.params_refused <= 3 or self.params_refused % 100 == 0:
                self.log.warning("refused parameters from %s (#%d): %s; keeping the current ones",
                                 msg.sender, self.params_refused, refused)
            return
        with self._lock:
            cur = self._pending or self.params
            # a restarted learner (new incarnation) may resume at a lower version; a held
            # version no heartbeat vouched for gives way to the learner's own (see _fence);
            # a rebroadcast of the held version carries the learner's newer backlog (_pace)
            if cur is None or b["incarnation"] != cur["incarnation"] or b["version"] >= cur["version"] \
                    or self._unvouched_gives_way(cur, b):
                self._pending = b

    def _on_learner_status(self, _key: str, payload: bytes) -> None:
        msg = self.decode(payload, "status")
        if msg is not None and msg.body["role"] == "learner":
            with self._lock:
                self._vouched = int(msg.body["version"])

    def _fence(self, b: dict) -> str | None:
        """Parameter versions are fenced like Raft terms: they move forward in
        steps the learner's heartbeats vouch for. A version is vouched once the
        learner's newest heartbeat reports at least it. A message may be at most
        ``actor.max_version_step`` above the newest vouched version (the
        heartbeat's, or the held one's if vouched), in its incarnation or a new
        one (a restarted learner resumes just above every published version);
        a larger jump (a forged 10**12) is refused and counted. Before any
        heartbeat, the held version is the reference (trust on first use)."""
        cur = self._pending or self.params
        heard = self._vouched
        if cur is None and heard is None:
            return None
        ref = -1 if heard is None else heard
        if cur is not None and (heard is None or cur["version"] <= heard):
            ref = max(ref, int(cur["version"]))
        step = self.cfg.actor.max_version_step
        if b["version"] > ref + step:
            return (f"version {b['version']} jumps more than {step} above {ref}, the newest the learner's "
                    f"heartbeats vouch for")
        return None

    def _unvouched_gives_way(self, cur: dict, b: dict) -> bool:
        """Same incarnation, lower version: taken only when the held version is
        above what the learner's heartbeat reports and this one is not (a forged
        version inside the step bound is dropped at the next heartbeat, and the
        actors follow the real learner again)."""
        heard = self._vouched
        return heard is not None and b["incarnation"] == cur["incarnation"] \
            and cur["version"] > heard >= b["version"]

    def _check_params(self, body: dict) -> str | None:
        """Why a parameter message cannot drive this actor's trees, or None: the
        wire check accepts any float arrays; the trees need the run's method,
        shapes that fit this env, and a finite, non-negative SAIL penalty."""
        if body["method"] != self.cfg.method:
            return f"method {body['method']!r} is not this run's {self.cfg.method!r}"
        try:
            body["params"] = ValidatedParams(body["params"])   # checked once, run every step
        except InvalidParams as exc:
            return str(exc)
        spec = body["params"].spec
        want = (N_CARRIERS, self.obs_dim, CARRIER_ACT_DIM)
        if (spec.n_agents, spec.obs_dim, spec.act_dim) != want and self.obs_dim is not None:
            return f"trees for (carriers, obs_dim, act_dim) = {spec[:3]}, this env needs {want}"
        if not body["settings"].get("kappa", 0.0) >= 0.0:
            return "negative kappa"
        return None

    def _adopt_params(self) -> None:
        with self._lock:
            if self._pending is not None:
                self.params, self._pending = self._pending, None
                self.m.version.labels(**self.labels).set(self.params["version"])

    def status_fields(self) -> dict:
        sr = float(np.mean(self.recent_success)) if self.recent_success else None
        return {"version": self.params["version"] if self.params else -1, "env_steps": self.env_steps,
                "env_steps_per_s": self.steps_rate.rate(), "success_rate": sr,
                "shield_p99_s": self.rtt.quantile(0.99),
                "extra": {"shield_failures": float(self.shield_failures), "chunks": float(self.chunks_sent),
                          "answers_refused": float(sum(self.answers_refused.values())),
                          "params_refused": float(self.params_refused),
                          "params_fenced": float(self.params_fenced),
                          "chunks_discarded": float(self.chunks_discarded),
                          "steps_discarded": float(self.steps_discarded),
                          "K": float(self.cfg.envs_per_actor),
                          # where the rollout loop's time goes: blocked on shield answers,
                          # and its thread's CPU time (the rest: pacing waits, descheduled)
                          "shield_wait_s_total": self.shield_wait_s, "loop_cpu_s_total": self.loop_cpu_s}}

    # ------------------------------------------------------------- shield
    def ask_shield(self, a_prop: np.ndarray, rows: SafetyRows) -> tuple:
        """Send the query for ``a_prop`` now; its replies queue up until
        ``filter_actions(..., asked=...)`` collects them. Rows the action box
        satisfies everywhere are not sent (``actor.prune_rows``; exact, the QP
        never needs them); the answer is still checked against all of them."""
        payload = self.encode("shield_req", {"a_prop": a_prop, **self.query_rows(a_prop, rows).as_dict()})
        return payload, time.perf_counter(), self.bus.replies(self.shield_key, payload,
                                                               timeout=self.cfg.actor.shield_timeout_s)

    def query_rows(self, a_prop: np.ndarray, rows: SafetyRows) -> SafetyRows:
        """The rows the QP is asked with: without those the box satisfies
        everywhere (``actor.prune_rows``), which it can never need."""
        return drop_box_redundant_rows(a_prop, rows) if self.cfg.actor.prune_rows else rows

    def filter_actions(self, a_prop: np.ndarray, rows: SafetyRows,
                       asked: tuple | None = None) -> tuple[np.ndarray, np.ndarray] | None:
        """Exact joint CBF-QP via the shield service: ``(a_exec, status)`` of the
        first answer that passes the actor's own check against ``rows``
        (common/shield/verify.py); asks again until one does. ``asked``: a
        query already sent by ``ask_shield``. Returns None only if a stop was
        requested (then nothing is executed)."""
        payload, t0, replies = asked if asked is not None else self.ask_shield(a_prop, rows)
        acfg = self.cfg.actor
        first_fail = None
        backoff = 0.01
        while not self.stop.is_set():
            why = "no reply (shield unreachable or timed out)"
            for reply in self._waited(replies):
                if reply.ok is None:
                    why = "shield error: " + reply.err.decode(errors="replace")[:200]
                    continue
                msg = self.decode(reply.ok, "shield_rep")
                if msg is None:
                    why = "undecodable reply"
                    continue
                refused = verify_answer(a_prop, rows, msg.body["a_exec"], msg.body["status"],
                                        tol=acfg.verify_tol, backend=self.cfg.shield.backend)
                if refused is not None:
                    self._refuse(refused, msg.sender)
                    why = f"answer refused ({refused}) from {msg.sender}"
                    continue
                dt = time.perf_counter() - t0
                self.rtt.add(dt)
                self.m.roundtrip.labels(**self.labels).observe(dt)
                if self.state == "unhealthy":
                    self.log.info("shield answers again; healthy")
                    self.state = "running"
                    self.m.healthy.labels(**self.labels).set(1)
                return np.asarray(msg.body["a_exec"], dtype=np.float64), np.asarray(msg.body["status"])
            # fail closed: count, wait, retry; never fall back to a_prop
            self.shield_failures += 1
            self.m.shield_timeouts.labels(**self.labels).inc()
            now = time.monotonic()
            first_fail = first_fail if first_fail is not None else now
            if now - first_fail > acfg.unhealthy_after_s and self.state != "unhealthy":
                self.state = "unhealthy"
                self.m.healthy.labels(**self.labels).set(0)
                text = f"no shield answer for {now - first_fail:.1f} s ({why}); executing nothing"
                self.log.error(text)
                self.publish_status(force=True, message=text)
                if acfg.exit_on_unhealthy:
                    raise ActorUnhealthy(text)
            elif self.shield_failures <= 3 or self.shield_failures % 100 == 0:
                self.log.warning("shield query failed (%s); retrying, nothing executed", why)
            self.publish_status()
            if self.stop.wait(backoff):
                break
            backoff = min(backoff * 2, 0.5)
            t0, replies = time.perf_counter(), self.bus.replies(self.shield_key, payload,
                                                                timeout=acfg.shield_timeout_s)
        return None

    def _waited(self, replies):
        """The replies, the time blocked on each counted in ``shield_wait_s``."""
        it = iter(replies)
        while True:
            t0 = time.perf_counter()
            reply = next(it, None)
            self.shield_wait_s += time.perf_counter() - t0
            if reply is None:
                return
            yield reply

    def _refuse(self, reason: str, sender: str) -> None:
        self.answers_refused[reason] += 1
        self.m.answers_rejected.labels(**self.labels, reason=reason).inc()
        n = self.answers_refused[reason]
        if n <= 3 or n % 100 == 0:
            self.log.warning("refused a shield answer from %s (%s, #%d); nothing executed", sender, reason, n)

    # ------------------------------------------------------------- loop
    def _make_envs(self) -> list:
        """One BatchEnv of K envs, or a pipelined actor's two groups (K - K//2 and
        K//2 envs) with seed streams of their own."""
        cfg, seed = self.cfg, self.cfg.seed * 1000 + self.actor_id
        K = cfg.envs_per_actor
        if not self.pipelined:
            return [BatchEnv(cfg.env_config(), K, seed=seed)]
        return [BatchEnv(cfg.env_config(), n, seed=[seed, g]) for g, n in enumerate((K - K // 2, K // 2))]

    def run(self) -> int:
        envs = self.envs if self.envs is not None else self._make_envs()
        self.obs_dim = int(envs[0].obs_dim)
        self.bus.subscribe(keys.status(self.cfg.run_id, "learner", 0), self._on_learner_status)
        self.bus.subscribe(keys.params(self.cfg.run_id), self._on_params)
        self.listen_control()
        self.m.healthy.labels(**self.labels).set(1)
        self.state = "waiting"
        t_wait = time.monotonic()
        while self.params is None and not self.stop.is_set():
            self._adopt_params()
            self.publish_status()
            if time.monotonic() - t_wait > self.cfg.actor.params_wait_s and self.state != "unhealthy":
                self.state = "unhealthy"
                self.m.healthy.labels(**self.labels).set(0)
                self.log.error("no parameters after %.0f s", self.cfg.actor.params_wait_s)
                self.publish_status(force=True, message="no parameters from the learner")
                if self.cfg.actor.exit_on_unhealthy:
                    return EXIT_UNHEALTHY
            self.stop.wait(0.02)
        self.state = "running"
        try:
            self._rollout(envs)
        except ActorUnhealthy:
            return EXIT_UNHEALTHY
        finally:
            self.state = "stopped"
            self.publish_status(force=True)
        return 0

    def _rollout(self, envs: list) -> None:
        outs = [e.reset() for e in envs]
        buf: dict[str, list] = {k: [] for k in wire.TRAJ_STEP_FIELDS}
        versions: list[int] = []
        episodes: list[dict] = []
        chunk_incarnation = None
        T = self.cfg.chunk_len
        sent = None   # every group's proposal (and query) for the coming step, made with ``params_msg``
        cpu0 = time.thread_time()
        while not self.stop.is_set():
            self.loop_cpu_s = time.thread_time() - cpu0
            if sent is None:   # pipeline empty: at the start, at chunk ends, after a learner restart
                self._adopt_params()
                if not versions:
                    self._pace()
                params_msg = self.params
                sent = [self._propose_group(out, params_msg) for out in outs]
            if versions and params_msg["incarnation"] != chunk_incarnation:
                # learner restarted: its resumed policy starts a fresh chunk (the
                # partial one was made with parameters the new learner never issued)
                self.chunks_discarded += 1
                self.steps_discarded += len(versions) * self.cfg.envs_per_actor
                buf = {k: [] for k in wire.TRAJ_STEP_FIELDS}
                versions, episodes = [], []
            chunk_incarnation = params_msg["incarnation"]
            stepped = self._step_groups(envs, outs, sent, params_msg, refill=len(versions) + 1 < T)
            if stepped is None:   # stopping: the partial chunk is dropped
                return
            records, outs, sent, next_params_msg = stepped
            for k in wire.TRAJ_STEP_FIELDS:  # copy: envs may reuse their output buffers
                buf[k].append(np.concatenate([np.asarray(r[k]) for r in records]) if len(records) > 1
                              else np.array(records[0][k], copy=True))
            versions.append(params_msg["version"])
            K = sum(len(r["a_exec"]) for r in records)
            self.env_steps += K
            self.steps_taken += 1
            if self.cfg.actor.trace_every and self.steps_taken % self.cfg.actor.trace_every == 0:
                self._publish_trace(records, params_msg["version"])
            self.steps_rate.add(self.env_steps)
            self.m.env_steps.labels(**self.labels).inc(K)
            for ep in (ep for nxt in outs for ep in nxt.get("episodes", [])):
                # numbers only; non-finite entries (completion_time of a failed
                # episode is NaN) are left out rather than failing the chunk
                ep = {k: float(v) for k, v in ep.items()
                      if isinstance(v, (int, float, np.number, bool, np.bool_)) and np.isfinite(float(v))}
                episodes.append(ep)
                self.m.episodes.labels(**self.labels).inc()
                if "success" in ep:
                    self.recent_success.append(ep["success"])
            if self.recent_success:
                self.m.success_rate.labels(**self.labels).set(float(np.mean(self.recent_success)))
            if len(versions) == T:
                last = {k: np.concatenate([np.asarray(o[k]) for o in outs]) for k in ("state", "obs")}
                self._publish_chunk(buf, versions, episodes, last)
                buf = {k: [] for k in wire.TRAJ_STEP_FIELDS}
                versions, episodes = [], []
            params_msg = next_params_msg
            self.publish_status()

    def _propose_group(self, out: dict, params_msg: dict) -> tuple:
        """One group's proposal with parameters ``params_msg`` (Eq. action_chain); a
        pipelined actor sends its shield query at once (a synchronous one when
        it needs the answer, in ``filter_actions``)."""
        kappa = float(params_msg["settings"].get("kappa", 0.0)) if self.uses_sail else 0.0
        rows = SafetyRows.of(out)
        prop = self._propose(params_msg["params"], out["obs"], rows, out["human_action"], self.rng, "train",
                             kappa=kappa, use_sail=self.uses_sail)
        a_prop = np.asarray(prop["a_prop"], dtype=np.float64)
        asked = self.ask_shield(a_prop, rows) if self.shielded and self.pipelined else None
        return prop, a_prop, rows, asked

    def _step_groups(self, envs: list, outs: list[dict], sent: list[tuple], params_msg: dict, refill: bool):
        """Execute one step of every env group, proposed (and, pipelined, asked)
        in ``sent`` with parameters ``params_msg``: each group waits for its verified
        answer and steps physics. Pipelined with ``refill`` (the chunk goes on),
        each group proposes its next step and sends that query right after
        stepping, so group 0's query is out while group 1 steps and the other
        way round (Sample Factory's double buffering). Both groups' next step
        uses the same parameters, adopted once after group 0 stepped; a learner
        restart (new incarnation) empties the pipeline instead, so the partial
        chunk is dropped before anything of the new policy is proposed.
        Returns ``(records, next outputs, next sent or None, next params_msg)``, or None
        if stopping (nothing more is executed)."""
        if self._chaos is not None and self._chaos.random() < self.cfg.actor.chaos_crash_prob:
            self.log.error("chaos: crashing on purpose (actor.chaos_crash_prob)")
            os._exit(EXIT_CHAOS)   # like a killed process: no cleanup, no last chunk
        refill = refill and self.pipelined
        records, nxts, next_sent, next_params_msg = [], [], [], params_msg
        for g, (env, out, (prop, a_prop, rows, asked)) in enumerate(zip(envs, outs, sent)):
            if not self.shielded:
                a_exec, shield_status = a_prop, np.full(len(a_prop), UNSHIELDED)
            else:
                verified = self.filter_actions(a_prop, rows, asked)
                if verified is None:
                    return None
                a_exec, shield_status = verified
            nxt = env.step(a_exec)
            records.append({"obs": out["obs"], "state": out["state"], "C": out["C"], "c": out["c"],
                            "row_mask": out["row_mask"], "fixed_mask": out["fixed_mask"],
                            "a_st": prop["a_st"], "a_bar": prop["a_bar"], "a_prop": a_prop, "a_exec": a_exec,
                            "shield_status": shield_status,
                            "logp": prop["logp"], "leaf": prop["leaf"], "reward": nxt["reward"],
                            "terminated": nxt["terminated"], "truncated": nxt["truncated"],
                            "final_state": nxt["final_state"], "final_obs": nxt["final_obs"],
                            "nodes": prop["nodes"], "sides": prop["sides"]})   # decision traces only
            nxts.append(nxt)
            if refill and g == 0:
                self._adopt_params()
                next_params_msg = self.params
                refill = next_params_msg["incarnation"] == params_msg["incarnation"]
            if refill:
                next_sent.append(self._propose_group(nxt, next_params_msg))
        return records, nxts, (next_sent if refill else None), next_params_msg

    def _publish_trace(self, records: list[dict], version: int) -> None:
        """The step's decisions for `sage watch` (wire kind ``trace``)."""
        cat = lambda k: np.concatenate([np.asarray(r[k]) for r in records])   # noqa: E731
        body = {"actor_id": self.actor_id, "version": int(version), "env_steps": self.env_steps,
                "every": self.cfg.actor.trace_every, "leaf": cat("leaf").astype(np.int32),
                "nodes": cat("nodes").astype(np.int32), "sides": cat("sides").astype(bool),
                "correction_norm": np.linalg.norm(cat("a_exec") - cat("a_prop"), axis=1)}
        self.send(keys.trace(self.cfg.run_id, self.actor_id), "trace", body)

    def _pace(self) -> None:
        """Before a new chunk: wait while ``max_chunks_ahead`` chunks already used
        the current version (the learner has not caught up yet), or while that
        many of this actor's chunks are not yet settled by the learner: a chunk
        started then would wait behind them and go stale unused."""
        acfg = self.cfg.actor
        t0 = time.monotonic()
        while not self.stop.is_set():
            params_msg = self.params
            ahead = sum(1 for v, inc, _ in self._sent_chunks
                        if v >= params_msg["version"] and inc == params_msg["incarnation"])
            if (ahead < acfg.max_chunks_ahead and self._unsettled(params_msg) < acfg.max_chunks_ahead) \
                    or time.monotonic() - t0 > acfg.pace_timeout_s:
                return
            self.publish_status()
            self.stop.wait(0.005)
            self._adopt_params()

    def _unsettled(self, params_msg: dict) -> int:
        """This actor's chunks the learner has not used or dropped yet, by its
        broadcast ``params_msg``: those sent under its incarnation after the last one it
        admitted (in flight or in its inbox) plus those it holds waiting."""
        received, waiting = params_msg.get("chunks_received"), params_msg.get("chunks_waiting")
        if received is None or waiting is None or self.actor_id >= len(received):
            return 0   # a learner that does not report its backlog: the version rule alone
        last = int(received[self.actor_id])
        in_flight = sum(1 for _, inc, seq in self._sent_chunks if inc == params_msg["incarnation"] and seq > last)
        return in_flight + max(0, int(waiting[self.actor_id]))

    def _publish_chunk(self, buf, versions, episodes, last) -> None:
        body = {k: np.stack([np.asarray(x) for x in buf[k]]).astype(TRAJ[k].send_dtype, copy=False)
                for k in wire.TRAJ_STEP_FIELDS}
        body.update({
            "actor_id": self.actor_id, "version": int(min(versions)),
            "incarnation": self.params["incarnation"], "env_steps": self.env_steps,
            "version_t": np.asarray(versions, dtype=np.int64),
            "last_state": np.asarray(last["state"], dtype=TRAJ["last_state"].send_dtype),
            "last_obs": np.asarray(last["obs"], dtype=TRAJ["last_obs"].send_dtype),
            "episodes": episodes,
        })
        self.send(keys.traj(self.cfg.run_id, self.actor_id), "traj", body)
        self.chunks_sent += 1
        self._sent_chunks.append((int(max(versions)), self.params["incarnation"], self._seq["traj"] - 1))
