"""Learner service: on-policy batches from trajectory chunks with bounded
staleness, ``Method.update``, versioned parameter broadcasts, atomic
checkpoints and resume, per-update metrics as JSONL + CSV (and TensorBoard
event files under ``<run_dir>/tb/`` when tensorboardX is installed).

Staleness: a chunk whose oldest parameter version is below
``version - max_lag`` is dropped (counted as ``stale``); a chunk made with
another learner incarnation's parameters (before a restart) is dropped
(``incarnation``). A batch is ``batch_chunks`` chunks concatenated along the
env axis (``common.wire.traj_batch``).
"""
from __future__ import annotations

import csv
import io
import json
import math
import queue
import secrets
import time
from collections import deque
from pathlib import Path

import numpy as np
import torch

from common import keys
from common.algos.methods import Method, make_method
from common.checkpoint import load_latest, save_checkpoint
from common.env.batch_env import BatchEnv
from common.evaluation.deployment import evaluate_policy
from common.rundir import RunDir, atomic_write_text, read_jsonl
from common.safety_rows import SafetyRows
from common.wire import traj_batch
from services.base import RateMeter, Service
from services.config import DEPLOY_PROBE_SEED
from services.learner.tracking import EventFile, tensorboard_available, x_of  # noqa: F401 - tensorboard_available: sage.train


CHUNK_OUTCOMES = ("used", "stale", "incarnation", "shape", "future", "actor_id", "overflow", "queue_full",
                  "lost", "actor_restarts", "duplicate", "seq_jump", "unused_restart")


class MetricsLog:
    """Per-update rows to ``metrics.jsonl`` and ``metrics.csv`` (CSV is
    rewritten atomically when a new column appears, so every row has every column)
    and, with ``tensorboard`` and tensorboardX importable, as TensorBoard scalars
    under ``tb/`` (``services.learner.tracking``: one per numeric key, tagged by
    section, at the row's env steps; ``config`` as text and HParams).

    On resume from a checkpoint taken after update ``upto``, rows of later
    updates (work the restart rolled back) move to ``metrics_discarded.jsonl``,
    marked with the restart, so ``metrics.jsonl`` never holds an update twice; a
    torn last line (a killed learner) is dropped. The event files continue in the
    same ``tb/`` directory, with the rolled-back steps purged for TensorBoard."""

    def __init__(self, run_dir: str | Path, upto: int | None = None, marker: dict | None = None,
                 tensorboard: bool = False, events_suffix: str = "", config: dict | None = None):
        run = RunDir(run_dir)
        run.root.mkdir(parents=True, exist_ok=True)
        self.jsonl, self.csv = run.metrics_jsonl, run.metrics_csv
        self.rows: list[dict] = read_jsonl(self.jsonl)  # resume: keep the earlier rows in the CSV too
        rolled_back = [r for r in self.rows if upto is not None and r.get("update", 0) > upto]
        if rolled_back:
            with open(run.metrics_discarded, "a") as f:
                for r in rolled_back:
                    f.write(json.dumps({**r, **(marker or {})}) + "\n")
            self.rows = [r for r in self.rows if r.get("update", 0) <= upto]
        if rolled_back or self.jsonl.exists():
            atomic_write_text(self.jsonl, "".join(json.dumps(r) + "\n" for r in self.rows))
        self.rolled_back = len(rolled_back)
        self.columns: list[str] = []
        for r in self.rows:
            self.columns += [k for k in r if k not in self.columns]
        if self.rows:
            self._rewrite_csv()
        self.events: EventFile | None = None
        if tensorboard and tensorboard_available():
            # purge from the first env step after the kept rows (the rolled-back updates' steps)
            purge = None if upto is None else (x_of(self.rows[-1]) + 1 if self.rows else 0)
            self.events = EventFile(run.tensorboard, events_suffix, purge, config)

    def _rewrite_csv(self) -> None:
        buf = io.StringIO()
        w = csv.DictWriter(buf, fieldnames=self.columns)
        w.writeheader()
        w.writerows(self.rows)
        atomic_write_text(self.csv, buf.getvalue())

    def append(self, row: dict) -> None:
        row = {k: (float(v) if isinstance(v, (np.floating, np.integer)) else v) for k, v in row.items()}
        self.rows.append(row)
        with open(self.jsonl, "a") as f:
            f.write(json.dumps(row) + "\n")
        new = [k for k in row if k not in self.columns]
        if new or not self.csv.exists():
            self.columns += new
            self._rewrite_csv()
        else:
            with open(self.csv, "a", newline="") as f:
                csv.DictWriter(f, fieldnames=self.columns).writerow(row)
        if self.events is not None and "update" in row:
            self.events.row(row)

    def close(self) -> None:
        if self.events is not None:
            self.events.close()


def build_method(cfg) -> Method:
    """The run's learning method, sized by the run's environment."""
    probe = BatchEnv(cfg.env_config(), 1, seed=cfg.seed)  # only for obs/state dims
    return make_method(cfg.method, cfg.algo_config(), probe.obs_dim, probe.state_dim)


def _episode_summary(episodes: list[dict]) -> dict:
    if not episodes:
        return {"episodes": 0}
    out = {"episodes": len(episodes)}
    for k in ("success", "return", "collision_steps", "length", "drop", "truncated", "deadlock"):
        vals = [e[k] for e in episodes if k in e]
        if vals:
            out[f"ep_{k}_mean"] = float(np.mean(vals))
    # the paper's per-update safety figures over the episodes that ended in this batch
    steps = sum(e.get("steps", e.get("length", 0)) for e in episodes)   # env episodes: "steps"
    if steps and all("collision_steps" in e for e in episodes):
        out["col_per_1k"] = 1000.0 * sum(e["collision_steps"] for e in episodes) / steps
    if steps and all("margin_violation_steps" in e for e in episodes):   # barrier < 0 of the shield's own spec
        out["margin_col_per_1k"] = 1000.0 * sum(e["margin_violation_steps"] for e in episodes) / steps
    if "ep_drop_mean" in out:
        out["drop_rate"] = out["ep_drop_mean"]
    return out


class LearnerService(Service):
    role = "learner"

    def __init__(self, cfg, bus, member_id=0, registry=None, stop=None, method=None):
        super().__init__(cfg, bus, member_id, registry, stop)
        self.method = method
        self.incarnation = secrets.token_hex(6)
        self.version = 0
        self.updates = 0
        self.env_steps = 0
        # bounded: a flood (or a slow update) drops chunks, counted, instead of growing memory
        self.chunks: queue.Queue[tuple[str, bytes]] = queue.Queue(maxsize=cfg.learner_queue_chunks)
        self.pending: deque[dict] = deque()
        # chunk outcomes; "lost" counts chunks an actor sent that never reached an update
        # here (gaps in its chunk sequence: sent while this learner was down, or received
        # by a previous incarnation after its last checkpoint)
        self.counts = {k: 0 for k in CHUNK_OUTCOMES}
        self.last_seq: dict[str, int] = {}       # actor sender -> newest chunk seq seen
        self.last_seq_t: dict[str, float] = {}   # actor sender -> that chunk's send time (header t)
        self._recent: dict[str, deque[tuple[int, float]]] = {}   # (seq, t) of each actor's recent chunks
        self.unfiltered_steps = 0                # shielded steps whose a_exec broke a row (audit; must stay 0)
        self.paths = RunDir(cfg.run_dir)
        self._published_floor = -1
        self.steps_rate = RateMeter()
        self.recent_success: deque[float] = deque(maxlen=100)
        self.run_dir = Path(cfg.run_dir)
        self.ckpt_dir = self.paths.checkpoints
        self.resumed_from: int | None = None
        self._t_start = time.monotonic()
        self._t_params = -1e9
        self.log_rows: MetricsLog | None = None
        self.last_deploy_sr: float | None = None   # newest deployment probe (status line)
        self.update_s_total = 0.0   # seconds inside method.update (the rest of the loop waits for data)

    # ------------------------------------------------------------- status
    def status_fields(self) -> dict:
        sr = float(np.mean(self.recent_success)) if self.recent_success else None
        extra = {f"chunks_{k}": float(v) for k, v in self.counts.items()}
        extra["unfiltered_steps"] = float(self.unfiltered_steps)
        extra["queue_depth"] = float(self.chunks.qsize())
        extra["update_s_total"] = self.update_s_total
        extra["budget_updates"], extra["progress"] = float(self.cfg.updates), self.progress()   # live line n/N, ETA
        if self.last_deploy_sr is not None and np.isfinite(self.last_deploy_sr):
            extra["deploy_sr"] = float(self.last_deploy_sr)
        return {"version": self.version, "env_steps": self.env_steps, "updates": self.updates,
                "env_steps_per_s": self.steps_rate.rate(), "success_rate": sr, "extra": extra}

    # ------------------------------------------------------------- params / checkpoints
    def publish_params(self) -> None:
        settings = {k: float(v) for k, v in self.method.actor_settings(self.progress()).items()}
        self.send(keys.params(self.cfg.run_id), "params", {
            "version": self.version, "incarnation": self.incarnation, "method": self.cfg.method,
            "params": {k: np.asarray(v) for k, v in self.method.policy_params().items()
                       if np.asarray(v).dtype.kind in "fiub"},
            "settings": settings, **self.backlog()})
        if self.version > self._published_floor:   # once per new version, before anyone can act on it
            self._published_floor = self.version
            atomic_write_text(self.paths.learner_version, json.dumps(
                {"version": self.version, "incarnation": self.incarnation}))
        self._t_params = time.monotonic()
        self.m.version.labels(**self.labels).set(self.version)

    def backlog(self) -> dict[str, np.ndarray]:
        """Per actor id: the sequence number of its last admitted chunk (-1: none)
        and its chunks waiting unused, broadcast with the parameters so that an
        actor starts a chunk only when it will be used (demand pacing, see
        ``ActorConfig.max_chunks_ahead``)."""
        n = self.cfg.actors
        waiting = np.bincount(np.asarray([b["actor_id"] for b in self.pending], dtype=np.int64), minlength=n)[:n]
        received = [self.last_seq.get(f"actor/{i}", -1) for i in range(n)]
        return {"chunks_received": np.asarray(received, dtype=np.int64),
                "chunks_waiting": waiting.astype(np.int64)}

    def checkpoint(self) -> Path:
        np_state = np.random.get_state()
        payload = {
            "method": self.method.state_dict(),
            "version": self.version,
            "updates": self.updates,
            "env_steps": self.env_steps,
            # chunks admitted but not yet used are gone for a learner resumed from here:
            # counted, so that every chunk of an actor's sequence has exactly one outcome
            "counts": {**self.counts, "unused_restart": self.counts["unused_restart"] + len(self.pending)},
            "last_seq": dict(self.last_seq),
            "last_seq_t": dict(self.last_seq_t),
            "unfiltered_steps": self.unfiltered_steps,
            "rng": {"torch": torch.get_rng_state(),
                    "numpy_mt19937": torch.from_numpy(np_state[1].astype(np.int64)),
                    "numpy_pos": int(np_state[2])},
            "config": self.cfg.to_json(),
            "time": time.time(),
        }
        return save_checkpoint(self.ckpt_dir, self.version, payload, keep=self.cfg.checkpoint_keep)

    def published_floor(self) -> int:
        """The highest version any learner of this run published (-1: none)."""
        try:
            return int(json.loads(self.paths.learner_version.read_text())["version"])
        except (FileNotFoundError, ValueError, KeyError, TypeError):
            return -1

    def try_resume(self) -> bool:
        ck = load_latest(self.ckpt_dir) if self.cfg.resume else None
        if ck is None:
            # no checkpoint yet: still never reuse a version an earlier incarnation published
            self.version = self.published_floor() + 1
            return False
        self._check_tree_settings(ck)
        self.method.load_state_dict(ck["method"])
        torch.set_rng_state(ck["rng"]["torch"])
        np.random.set_state(("MT19937", ck["rng"]["numpy_mt19937"].numpy().astype(np.uint32),
                             ck["rng"]["numpy_pos"], 0, 0.0))
        self.resumed_from = int(ck["version"])
        # a fresh version for the restored policy, above every version published so
        # far (the previous incarnation may have gone on past its checkpoint)
        self.version = max(self.resumed_from, self.published_floor()) + 1
        self.updates = int(ck["updates"])
        self.env_steps = int(ck["env_steps"])
        self.counts.update({k: int(v) for k, v in ck["counts"].items() if k in self.counts})
        self.last_seq = {str(k): int(v) for k, v in ck.get("last_seq", {}).items()}
        self.last_seq_t = {str(k): float(v) for k, v in ck.get("last_seq_t", {}).items()}
        self.unfiltered_steps = int(ck.get("unfiltered_steps", 0))
        self.log.info("resumed from checkpoint version %d (update %d)", self.resumed_from, self.updates)
        return True

    TREE_SETTINGS = {"tree_depth": 4, "split_k": 0, "leaf_k": 0}   # absent from a checkpoint = its value then

    def _check_tree_settings(self, ck: dict) -> None:
        """Refuse a checkpoint whose trees mean something else under this config:
        the state holds dense straight-through weights, so the same tensors under
        another ``split_k`` are another policy (seen: a k=1 run resumed dense went
        from SR 1.0 to 0.0)."""
        try:
            saved = json.loads(ck.get("config") or "{}").get("algo", {})
        except (TypeError, ValueError):
            saved = {}
        for key, absent in self.TREE_SETTINGS.items():
            was, now = saved.get(key, absent), getattr(self.cfg.algo, key)
            if was != now:
                raise ValueError(f"{self.ckpt_dir}: its trees were trained with algo.{key} = {was}, this run has "
                                 f"{now}; resume with --set algo.{key}={was} or start a new run directory")

    # ------------------------------------------------------------- budget
    def progress(self) -> float:
        p = self.updates / self.cfg.updates if self.cfg.updates > 0 else 0.0
        if self.cfg.minutes:
            p = max(p, (time.monotonic() - self._t_start) / (60.0 * self.cfg.minutes))
        return float(min(max(p, 0.0), 1.0))

    def budget_done(self) -> bool:
        if self.cfg.updates > 0 and self.updates >= self.cfg.updates:
            return True
        return bool(self.cfg.minutes) and time.monotonic() - self._t_start >= 60.0 * self.cfg.minutes

    def deploy_probe(self) -> dict:
        """What deployment would do now: hard trees' deterministic actions through the
        exact QP (unshielded for HAPPO) on held-out seeded episodes (Sec. III-D)."""
        t0 = time.perf_counter()
        e = evaluate_policy(self.method.policy_params(), self.cfg.env_config(), self.cfg.deploy_probe_episodes,
                            seed=DEPLOY_PROBE_SEED + self.cfg.seed, shielded=self.method.shielded,
                            max_steps=self.cfg.eval_max_steps or None)
        self.last_deploy_sr = e["success_rate"]
        return {"deploy_sr": e["success_rate"], "deploy_return": e["return_mean"],
                "deploy_col_per_1k": e["col_per_1k"], "deploy_drop_rate": e["drop_rate"],
                "deploy_truncation_rate": e["truncation_rate"],
                "deploy_correction": e["correction_mean"], "deploy_probe_s": time.perf_counter() - t0}

    # ------------------------------------------------------------- chunks
    def _on_traj(self, key: str, payload: bytes) -> None:
        try:
            # decode on the learner thread, not Zenoh's; the key's actor id goes along: under
            # the TLS profile with per-actor certificates only actor i may publish traj/<i>
            self.chunks.put_nowait((key.rsplit("/", 1)[-1], payload))
        except queue.Full:
            self._drop("queue_full")
            self.m.dropped.labels(**self.labels, queue="learner_chunks").inc()

    def _admit(self, msg, key_id: str | None = None) -> None:
        body = msg.body
        if not 0 <= body["actor_id"] < self.cfg.actors or msg.sender != f"actor/{body['actor_id']}" \
                or (key_id is not None and key_id != str(body["actor_id"])):
            self._drop("actor_id")   # not one of this run's actors: not part of any actor's sequence
            return
        replay = self._account_seq(msg.sender, msg.seq, msg.t)
        if replay:
            self._drop(replay)   # a copy, or a jump no actor makes: trains nothing, moves no count
            return
        versions = body["version_t"]
        if body["incarnation"] != self.incarnation:
            self._drop("incarnation")
        elif body["version"] > self.version or (versions.size and int(versions.max()) > self.version) \
                or (versions.size and int(versions.min()) != body["version"]):
            self._drop("future")   # claims parameters this learner never published
        elif body["version"] < self.version - self.cfg.max_lag:
            self._drop("stale")
        else:
            self.pending.append(body)
            while len(self.pending) > self.cfg.learner_queue_chunks:
                self.pending.popleft()   # the oldest would go stale first anyway
                self._drop("overflow")

    def _account_seq(self, sender: str, seq: int, t: float) -> str | None:
        """Chunks an actor sent that never arrived: gaps in its per-sender sequence
        (which starts at 0; one that starts over, sent later than the newest, is a
        restarted actor process). Returns why a chunk is not part of the sequence:
        ``duplicate`` (a chunk seen before, or an older one replayed: sent no later
        than the newest) or ``seq_jump`` (more than ``max_seq_gap`` ahead); those
        change no count but their own, so replays never inflate ``lost``."""
        recent = self._recent.setdefault(sender, deque(maxlen=64))
        if (seq, t) in recent:
            return "duplicate"
        last = self.last_seq.get(sender, -1)   # -1: every chunk before this one is missing
        restart = seq <= last
        if restart and t <= self.last_seq_t.get(sender, -math.inf):
            return "duplicate"
        gap = seq - (-1 if restart else last) - 1
        if gap > self.cfg.max_seq_gap:
            return "seq_jump"
        if restart:                              # the actor process restarted
            self.counts["actor_restarts"] += 1
        if gap > 0:
            self.counts["lost"] += gap
            self.m.chunks.labels(**self.labels, outcome="lost").inc(gap)
        self.last_seq[sender], self.last_seq_t[sender] = seq, t
        recent.append((seq, t))
        return None

    def _drop(self, why: str) -> None:
        self.counts[why] += 1
        self.m.chunks.labels(**self.labels, outcome=why).inc()

    def _audit_executed(self, batch: dict) -> dict:
        """An independent check of what the actors executed, from the chunks: a
        shielded step whose verified QP answer was OPTIMAL must meet every row of
        that step (Eq. qpshield). Counted, never trusted: the figure must stay 0."""
        status = np.asarray(batch["shield_status"]).reshape(-1)
        out = {"shield_infeasible_steps": int((status == 1).sum())}
        if self.method is not None and getattr(self.method, "shielded", False):
            rows = SafetyRows(*(np.asarray(batch[k]).reshape(-1, *np.shape(batch[k])[2:]) for k in SafetyRows.FIELDS))
            a_exec = np.asarray(batch["a_exec"]).reshape(-1, np.shape(batch["a_exec"])[-1])
            broken = rows.scaled_violation(a_exec) > self.cfg.actor.verify_tol
            bad = int((broken & (status == 0)).sum() + (status < 0).sum())   # unshielded steps too
            self.unfiltered_steps += bad
            out["unfiltered_steps"] = bad
        return out

    def drain(self) -> None:
        while True:
            try:
                key_id, payload = self.chunks.get_nowait()
            except queue.Empty:
                return
            msg = self.decode(payload, "traj")
            if msg is not None:
                self._admit(msg, key_id)

    def try_update(self) -> bool:
        # chunks may have become stale while waiting (an update happened)
        fresh = [b for b in self.pending if b["version"] >= self.version - self.cfg.max_lag]
        for _ in range(len(self.pending) - len(fresh)):
            self._drop("stale")
        self.pending = deque(fresh)
        n = self.cfg.batch_chunks
        if len(self.pending) < n:
            return False
        # the freshest chunks (most on-policy); older ones wait and go stale
        newest_first = sorted(self.pending, key=lambda b: b["version"], reverse=True)
        bodies, rest = newest_first[:n], newest_first[n:]
        self.pending = deque(sorted(rest, key=lambda b: b["version"]))
        try:
            batch = traj_batch(bodies)
        except ValueError as exc:
            self.log.warning("dropping %d chunks: %s", n, exc)
            for _ in bodies:
                self._drop("shape")
            return False
        for _ in bodies:
            self.counts["used"] += 1
            self.m.chunks.labels(**self.labels, outcome="used").inc()
        audit = self._audit_executed(batch)
        steps = int(batch["reward"].size)
        episodes = [e for b in bodies for e in b["episodes"]]
        for e in episodes:
            if "success" in e:
                self.recent_success.append(e["success"])
        lags = [self.version - b["version"] for b in bodies]
        step_lags = self.version - np.concatenate([np.asarray(b["version_t"]) for b in bodies])
        t0, cpu0 = time.perf_counter(), time.thread_time()
        diag = self.method.update(batch, self.progress())
        dt, cpu = time.perf_counter() - t0, time.thread_time() - cpu0
        self.update_s_total += dt
        self.updates += 1
        self.version += 1
        self.env_steps += steps
        self.steps_rate.add(self.env_steps)
        self.m.updates.labels(**self.labels).inc()
        self.m.update_seconds.labels(**self.labels).observe(dt)
        row = {"update": self.updates, "version": self.version, "env_steps": self.env_steps,
               "time_s": time.monotonic() - self._t_start, "update_s": dt,
               # the update's own thread CPU time: below update_s where other threads or
               # processes hold the core or the interpreter lock
               "update_cpu_s": cpu, "progress": self.progress(),
               "batch_T": int(batch["reward"].shape[0]), "batch_K": int(batch["reward"].shape[1]),
               # the data's policy lag (learner version - behaviour version of each step)
               "lag_max": int(max(lags)), "lag_min": int(step_lags.min()) if step_lags.size else int(min(lags)),
               "lag_mean": float(step_lags.mean()) if step_lags.size else float(np.mean(lags)),
               "chunks_stale": self.counts["stale"],
               "reward_mean": float(batch["reward"].mean()),
               "success_rate_recent": float(np.mean(self.recent_success)) if self.recent_success else None}
        row.update(_episode_summary(episodes))
        row.update(audit)
        row.update({k: float(v) for k, v in diag.items() if np.isscalar(v)})
        self.publish_params()   # first, so the actors roll out with it during the probe
        every = self.cfg.deploy_probe_every
        if every and self.updates % every == 0:
            row.update(self.deploy_probe())
        self.log_rows.append(row)
        if self.updates % self.cfg.checkpoint_every == 0:
            self.checkpoint()
        return True

    # ------------------------------------------------------------- loop
    def run(self) -> int:
        if self.cfg.torch_threads:
            torch.set_num_threads(self.cfg.torch_threads)  # process-wide: in-process the actor threads share it
        if self.method is None:
            self.method = build_method(self.cfg)
        resumed = self.try_resume()
        self.log_rows = MetricsLog(self.run_dir, upto=self.updates if resumed else 0,
                                   marker={"rolled_back_by": self.incarnation, "resumed_from": self.resumed_from},
                                   tensorboard=self.cfg.tensorboard, events_suffix=self.incarnation,
                                   config=json.loads(self.cfg.to_json()))
        if self.log_rows.rolled_back:
            self.log.warning("moved %d metrics rows past the checkpoint to %s", self.log_rows.rolled_back,
                             self.paths.metrics_discarded.name)
        if self.log_rows.events is not None:
            self.log.info("tensorboard: on, events in %s", self.paths.tensorboard)
        else:
            self.log.info("tensorboard: off (%s)", "tensorboard=false" if not self.cfg.tensorboard else
                          "tensorboardX not installed: pip install 'sage-transport[tensorboard]'")
        try:
            return self._loop()
        finally:
            self.log_rows.close()

    def _loop(self) -> int:
        self.bus.subscribe(keys.traj_all(self.cfg.run_id), self._on_traj)
        self.listen_control()
        self.state = "running"
        self.publish_params()
        self.publish_status(force=True)
        while not self.stop.is_set() and not self.budget_done():
            self.drain()
            if not self.try_update():
                self.stop.wait(0.005)
            if time.monotonic() - self._t_params > self.cfg.params_rebroadcast_s:
                self.publish_params()  # late joiners and lost samples
            self.publish_status()
        self.checkpoint()
        self.state = "done" if self.budget_done() else "stopped"
        self.publish_status(force=True)
        return 0

    def summary(self) -> dict:
        return {"version": self.version, "updates": self.updates, "env_steps": self.env_steps,
                "chunks": dict(self.counts), "resumed_from": self.resumed_from,
                "rejected": dict(self.rejected), "incarnation": self.incarnation}
