"""The one source of defaults for a training run and its services.

``TrainConfig`` is written resolved to ``<run_dir>/config.json`` by
``sage train`` and read back by every service entry point
(``python -m services.<role> --config RUN.json``). The environment and
algorithm configs belong to their owners (``common.env.EnvConfig``,
``common.algos.AlgoConfig``); this file only carries their overrides and, in
the resolved JSON, their full field values.
"""
from __future__ import annotations

import dataclasses
import json
import secrets
import time
from dataclasses import dataclass, field
from pathlib import Path

from common.algos.config import AlgoConfig
from common.algos.registry import ALL_METHODS
from common.env.config import EnvConfig
from common.keys import check_id
from common.rundir import atomic_write_text

# Evaluation seeds, disjoint from the training envs (1000 * seed + actor id) and each other.
FINAL_EVAL_SEED = 10_000
DEPLOY_PROBE_SEED = 30_000


@dataclass
class TransportConfig:
    """Zenoh endpoints. In-process mode ignores them (no network at all).

    TLS (deploy/README.md, "Secure deployment"): set all three ``tls_*``
    paths (PEM) and write endpoints as ``tls/<host>:<port>``; ``{role}`` in a
    path is replaced by the service's role, so one run config can name one
    certificate per role (``certs/{role}.pem``, CN = role). Empty = plain TCP.
    """

    mode: str = "peer"
    connect: list[str] = field(default_factory=list)   # e.g. ["tcp/10.0.0.1:7447"] (a router)
    listen: list[str] = field(default_factory=list)    # e.g. ["tcp/127.0.0.1:0"]
    tls_root_ca: str = ""        # CA certificate the router's certificate must chain to
    tls_cert: str = ""           # this process's certificate, e.g. "certs/{role}.pem"
    tls_key: str = ""            # its private key, e.g. "certs/{role}.key"
    tls_verify_name: bool = True  # the router's certificate must name the host in the endpoint
    # Largest message a Zenoh link of this run accepts (transport/link/rx/max_message_size,
    # on every session and the run's router) and services decode; 0 = the run's own bound
    # (TrainConfig.message_bytes_bound: its largest chunk, from T, K and M)
    max_message_bytes: int = 0


@dataclass
class PortsConfig:
    """Prometheus ports; 0 disables. Actor ``i`` uses ``actor_base + i``."""

    learner: int = 0
    shield: int = 0
    actor_base: int = 0
    inprocess: int = 0   # the single registry of `sage train --mode inprocess`
    bind: str = "127.0.0.1"   # address the metric servers listen on; "0.0.0.0" for remote scrapers


@dataclass
class ShieldConfig:
    max_batch: int = 256          # QP rows per solve_cbf_qp call
    window_s: float = 0.002       # wait at most this long for more requests once one arrived
    backend: str = "default"      # common.shield.qp.BACKENDS name
    # Queries waiting for a batch, at most (one per actor per step is the normal load;
    # beyond this a flood is answered "overloaded" at once and counted, memory stays bounded)
    max_queue: int = 1024
    # Decoded queries one sender may have waiting (a pipelined actor has 2 out per
    # step); beyond it that sender's query is answered "overloaded" and counted, so
    # one flooding sender cannot take the others' turns (service is round-robin)
    max_pending_per_sender: int = 4


@dataclass
class ActorConfig:
    shield_timeout_s: float = 1.0      # one query; no answer -> retry (nothing executed)
    # An answer executes only if it passes the actor's own check (common/shield/verify.py):
    # rows met to this tolerance (relative to max(1, ||C_i||)), box, human block untouched.
    # The exact QP meets rows to 1e-10; 1e-6 leaves room for float64 round-off only.
    verify_tol: float = 1e-6
    # Shield queries carry only the rows the action box does not satisfy everywhere
    # (common/shield/prune.py: exact, a dropped row can never be active or violated);
    # most wall rows are far from binding, and the rows are most of a query's bytes.
    prune_rows: bool = True
    # Parameter fencing (services/actor/service.py _fence): a params message may be at
    # most this many versions above the newest version the learner's heartbeats vouch
    # for (one update = one version; heartbeats come every status_period_s)
    max_version_step: int = 64
    unhealthy_after_s: float = 10.0    # no shield answer this long -> status "unhealthy"
    exit_on_unhealthy: bool = False    # supervised mode: exit(3) so the supervisor sees it
    params_wait_s: float = 60.0        # max wait for the first parameters before unhealthy
    # Pacing (bounded staleness at the source): an actor starts a new chunk only
    # while fewer than this many of its chunks were rolled out with its current
    # parameter version (1 = synchronous on-policy, 2 = one chunk of overlap) and
    # fewer than this many are unsettled at the learner (sent but not yet used or
    # dropped, from the backlog the learner broadcasts with its parameters).
    # Without the first rule actors outrun a slow learner and most chunks go stale;
    # without the second, a learner slower than its actors still drops about one
    # chunk in three as stale (measured: 56 of 156 in the main job), rolled out on
    # cores the learner needed.
    max_chunks_ahead: int = 2
    pace_timeout_s: float = 120.0      # a lost params message never deadlocks: roll out anyway
    # Fault injection (as RLlib's fault-injecting env): per env step, the actor process
    # exits abruptly with this probability. For supervised runs, which restart it; 0 = off.
    chaos_crash_prob: float = 0.0
    # Double-buffered sampling (as Sample Factory's): the K envs are two groups
    # that alternate, so one group's query is at the shield while the other group
    # steps physics. Same chunks (all K envs, one version per step), same
    # fail-closed rules; only the order of waiting changes. Needs K >= 2 and a
    # shielded method (without a shield there is no round trip to hide). It halves
    # the batch of every per-step call and doubles the queries, so it costs CPU:
    # on this 2-core host 21-70 more actor and 19-45 more shield and router
    # core-us per env step (two bench runs), and where the actor, shield and
    # learner share the cores that costs more than the waiting it hides
    # (2026-12-03: the main job 47-48 s pipelined vs 41 s synchronous; supervised
    # sage 3.2-3.3k vs 3.4-3.6k env steps/s; docs/scaling.md). So off by default;
    # turn it on where the shield's round trip is long against a step (another
    # host) and the actor has its cores.
    pipeline: bool = False
    # Live decision stream (`sage watch RUN`): every this many steps the actor
    # publishes the step's leaves, predicate paths and QP correction norms on
    # sage/<run>/trace/<actor>. 0 = off; 10 costs one small message per 10 steps.
    trace_every: int = 0


@dataclass
class TrainConfig:
    run_id: str = ""                   # filled with a fresh id by resolve()
    scenario: str = "narrow_gate"
    method: str = "sage"
    actors: int = 1
    # Shield shards: actor i asks shard i % shields on its own key (sage/<run>/shield/<k>),
    # so one shield process stops being the bottleneck once actors outgrow it
    # (docs/scaling.md). One shard serves a few actors at the training batch size.
    shields: int = 1
    # K x T = 1024 samples per update: on narrow_gate (2 cores, in-process) SAGE
    # reaches deployment SR 1.0 in 4 min with these (docs/results_narrow_gate.md)
    envs_per_actor: int = 32           # K
    chunk_len: int = 32                # T: steps per trajectory chunk
    chunks_per_update: int = 0         # 0 -> one chunk per actor
    updates: int = 100                 # budget in learner updates (~4 min on 2 cores: SAGE on narrow_gate learns to succeed) ...
    minutes: float | None = None       # ... or wall-clock minutes (whichever first)
    max_lag: int = 1                   # accept chunks from versions >= current - max_lag
    # A chunk whose sequence number is more than this many ahead of its actor's
    # last one is refused ("seq_jump") rather than counting the gap as lost: a
    # learner down for minutes misses far fewer (actors pace on its parameters)
    max_seq_gap: int = 4096
    learner_queue_chunks: int = 64     # bound of the learner's chunk queue and pending set (drops counted)
    seed: int = 0
    run_dir: str = ""                  # filled by resolve(): runs/<run_id>
    mode: str = "inprocess"            # inprocess | supervised
    checkpoint_every: int = 5          # updates between checkpoints (and at the end)
    checkpoint_keep: int = 3
    resume: bool = True                # learner resumes from run_dir/checkpoints if present
    status_period_s: float = 1.0
    params_rebroadcast_s: float = 0.5
    eval_episodes: int = 4             # final deterministic deployment eval (0 = skip)
    eval_max_steps: int = 0            # 0 -> env default episode length
    # Deployment probe during training: every this many updates the learner runs
    # the deterministic trees (+ exact QP when shielded) on a few held-out episodes
    # and logs deploy_sr & co. The stochastic training SR can hide a deterministic
    # policy that stalls (seen: SAGE on narrow_gate, training SR 0.9, deployment 0.0).
    deploy_probe_every: int = 20       # 0 = off
    deploy_probe_episodes: int = 8
    # torch intra-op threads of the learner (0 = torch's default). On 2 cores a
    # second torch thread fights the actor/shield threads: measured in-process
    # 10 s -> 1.8 s per 512-sample SAGE update with 1 thread.
    torch_threads: int = 1
    # TensorBoard event files of the metrics rows under <run_dir>/tb/, when the
    # optional tensorboardX is installed (`pip install 'sage-transport[tensorboard]'`)
    tensorboard: bool = True
    transport: TransportConfig = field(default_factory=TransportConfig)
    ports: PortsConfig = field(default_factory=PortsConfig)
    shield: ShieldConfig = field(default_factory=ShieldConfig)
    actor: ActorConfig = field(default_factory=ActorConfig)
    # The environment's and the learner's own configs. A map given here (constructor,
    # JSON) is a set of field overrides on their defaults. The run's scenario and seed
    # are the single sources: they win over env.scenario and algo.seed.
    env: EnvConfig = field(default_factory=EnvConfig)
    algo: AlgoConfig = field(default_factory=AlgoConfig)

    def __post_init__(self):
        if isinstance(self.env, dict):
            self.env = build_dataclass(EnvConfig, {**self.env, "scenario": self.scenario})
        if isinstance(self.algo, dict):
            self.algo = build_dataclass(AlgoConfig, {**self.algo, "seed": self.seed})

    # -------------------------------------------------------------- helpers
    def message_bytes_bound(self) -> int:
        """The largest message this run's services accept: ``transport.max_message_bytes``,
        or (0) a bound on its own largest message, a trajectory chunk of its T, K and M
        (``wire.traj_bytes_bound``; at least 8 MiB for parameters and everything else),
        never above ``wire.MAX_MESSAGE_BYTES``."""
        from common import wire
        from common.env.observations import OBS_DIM, STATE_DIM

        if self.transport.max_message_bytes > 0:
            return min(int(self.transport.max_message_bytes), wire.MAX_MESSAGE_BYTES)
        chunk = wire.traj_bytes_bound(self.chunk_len, self.envs_per_actor, self.env.max_rows, OBS_DIM, STATE_DIM)
        return min(max(chunk, 8 * 1024 * 1024), wire.MAX_MESSAGE_BYTES)

    def validate(self) -> "TrainConfig":
        # Types first (a config.json or an override may carry "x" for a number):
        # each plain field of this config and of its service sections must have
        # its default's type (an int is fine for a float, a bool is not an int).
        def check_types(obj, prefix: str) -> None:
            for f in dataclasses.fields(obj):
                value = getattr(obj, f.name)
                default = f.default if f.default is not dataclasses.MISSING else f.default_factory()
                if dataclasses.is_dataclass(default):
                    if f.name in ("transport", "ports", "shield", "actor"):
                        if not isinstance(value, type(default)):
                            raise ValueError(f"{prefix}{f.name} must be a map of {type(default).__name__} fields, "
                                             f"got {value!r}")
                        check_types(value, f"{f.name}.")
                    continue   # env / algo: validated by their owners
                if default is None:   # minutes: float | None
                    ok = value is None or (isinstance(value, (int, float)) and not isinstance(value, bool))
                    want = "a number or null"
                elif isinstance(default, bool):
                    ok, want = isinstance(value, bool), "true or false"
                elif isinstance(default, int):
                    ok, want = isinstance(value, int) and not isinstance(value, bool), "an integer"
                elif isinstance(default, float):
                    ok = isinstance(value, (int, float)) and not isinstance(value, bool)
                    want = "a number"
                elif isinstance(default, str):
                    ok, want = isinstance(value, str), "a string"
                elif isinstance(default, list):
                    ok = isinstance(value, list) and all(isinstance(v, str) for v in value)
                    want = "a list of strings"
                else:
                    continue
                if not ok:
                    raise ValueError(f"{prefix}{f.name} must be {want}, got {value!r}")

        check_types(self, "")
        check_id(self.run_id, "run id")
        self.env_config()   # EnvConfig rejects an unknown scenario (and names the known ones)
        if self.minutes is not None and not self.minutes > 0:
            raise ValueError(f"minutes must be > 0 when given, got {self.minutes}")
        for name in ("seed", "eval_episodes", "eval_max_steps", "checkpoint_keep"):
            if getattr(self, name) < 0:
                raise ValueError(f"{name} must be >= 0, got {getattr(self, name)}")
        if self.checkpoint_every < 1:
            raise ValueError(f"checkpoint_every must be >= 1, got {self.checkpoint_every}")
        for name in ("status_period_s", "params_rebroadcast_s"):
            if not getattr(self, name) > 0:
                raise ValueError(f"{name} must be > 0, got {getattr(self, name)}")
        for f in dataclasses.fields(self.ports):
            if isinstance(getattr(self.ports, f.name), int) and not 0 <= getattr(self.ports, f.name) <= 65535:
                raise ValueError(f"ports.{f.name} must be a port 0..65535 (0 = off), got {getattr(self.ports, f.name)}")
        for name in ("shield_timeout_s", "unhealthy_after_s", "params_wait_s", "pace_timeout_s"):
            if not getattr(self.actor, name) > 0:
                raise ValueError(f"actor.{name} must be > 0, got {getattr(self.actor, name)}")
        if not 0.0 <= self.actor.chaos_crash_prob < 1.0:
            raise ValueError(f"actor.chaos_crash_prob must be in [0, 1), got {self.actor.chaos_crash_prob}")
        if self.actor.chaos_crash_prob > 0 and self.mode != "supervised":
            raise ValueError("actor.chaos_crash_prob needs --mode supervised (a crashed thread is not restarted)")
        if self.actor.max_version_step < 1:
            raise ValueError(f"actor.max_version_step must be >= 1, got {self.actor.max_version_step}")
        if not self.actor.verify_tol > 0 or self.learner_queue_chunks < 1:
            raise ValueError("actor.verify_tol must be > 0 and learner_queue_chunks >= 1")
        if self.actor.trace_every < 0:
            raise ValueError(f"actor.trace_every must be >= 0 (0 = off), got {self.actor.trace_every}")
        if self.actor.max_chunks_ahead < 1:
            raise ValueError(f"actor.max_chunks_ahead must be >= 1, got {self.actor.max_chunks_ahead}")
        if self.method not in ALL_METHODS:
            raise ValueError(f"method {self.method!r} not in {ALL_METHODS}")
        if self.mode not in ("inprocess", "supervised"):
            raise ValueError(f"mode {self.mode!r} must be inprocess or supervised")
        for name in ("actors", "shields", "envs_per_actor", "chunk_len"):
            if getattr(self, name) < 1:
                raise ValueError(f"{name} must be >= 1, got {getattr(self, name)}")
        if self.updates < 1 and not self.minutes:
            raise ValueError(f"need a budget: updates >= 1 or minutes > 0, got updates {self.updates}")
        if self.torch_threads < 0:
            raise ValueError("torch_threads must be >= 0 (0 = torch default)")
        if self.deploy_probe_every < 0 or self.deploy_probe_episodes < 1:
            raise ValueError("deploy_probe_every must be >= 0 and deploy_probe_episodes >= 1")
        if self.transport.max_message_bytes < 0:
            raise ValueError(f"transport.max_message_bytes must be >= 0 (0: the run's own bound), "
                             f"got {self.transport.max_message_bytes}")
        if self.max_seq_gap < 1:
            raise ValueError(f"max_seq_gap must be >= 1, got {self.max_seq_gap}")
        if self.max_lag < 0 or self.chunks_per_update < 0:
            raise ValueError("max_lag and chunks_per_update must be >= 0")
        if self.shields > self.actors:
            raise ValueError(f"shields ({self.shields}) must be <= actors ({self.actors}): a shard without actors idles")
        if self.ports.shield and self.ports.actor_base and self.ports.shield < self.ports.actor_base \
                < self.ports.shield + self.shields:
            raise ValueError(f"shield shard metric ports {self.ports.shield}..{self.ports.shield + self.shields - 1} "
                             f"overlap the actors' from {self.ports.actor_base}")
        if self.shield.max_queue < 1 or self.shield.max_pending_per_sender < 1:
            raise ValueError(f"shield.max_queue and shield.max_pending_per_sender must be >= 1, got "
                             f"{self.shield.max_queue}, {self.shield.max_pending_per_sender}")
        if self.shield.max_batch < 1 or self.shield.window_s < 0:
            raise ValueError("shield.max_batch >= 1 and shield.window_s >= 0")
        return self

    @property
    def batch_chunks(self) -> int:
        return self.chunks_per_update or self.actors

    def shield_shard(self, actor_id: int) -> int:
        """The shield shard actor ``actor_id`` asks."""
        return int(actor_id) % self.shields

    def actors_of_shard(self, shard: int) -> int:
        """How many of the run's actors ask shard ``shard`` (ids 0 .. actors-1)."""
        return len(range(int(shard), self.actors, self.shields))

    def env_config(self) -> EnvConfig:
        return dataclasses.replace(self.env, scenario=self.scenario)

    def algo_config(self) -> AlgoConfig:
        return dataclasses.replace(self.algo, seed=self.seed)

    def override(self, section: str, key: str, value) -> None:
        """Set ``env.KEY`` or ``algo.KEY`` (validated by the owner dataclass)."""
        owner = {"env": EnvConfig, "algo": AlgoConfig}[section]
        if (section, key) in (("env", "scenario"), ("algo", "seed")):
            raise ValueError(f"{section}.{key} follows the run's own {key!r} field; set that instead")
        values = dataclasses.asdict(getattr(self, section))
        if key not in values:
            raise ValueError(f"unknown {owner.__name__} field {key!r}")
        setattr(self, section, build_dataclass(owner, {**values, key: value}))

    def resolve(self) -> "TrainConfig":
        """Fill run id / run dir; env and algo follow the run's scenario and seed."""
        if not self.run_id:
            self.run_id = time.strftime("%Y%m%d-%H%M%S") + "-" + secrets.token_hex(3)
        if not self.run_dir:
            self.run_dir = str(Path("runs") / self.run_id)
        self.env, self.algo = self.env_config(), self.algo_config()
        return self.validate()

    def to_json(self) -> str:
        return json.dumps(dataclasses.asdict(self), indent=2, sort_keys=True, default=_json_default)

    def save(self, path: str | Path) -> Path:
        """Atomically: other processes (services, `sage eval`) read it back."""
        return atomic_write_text(path, self.to_json() + "\n")

    @classmethod
    def from_dict(cls, d: dict) -> "TrainConfig":
        d = dict(d)
        nested = {"transport": TransportConfig, "ports": PortsConfig,
                  "shield": ShieldConfig, "actor": ActorConfig}
        known = {f.name for f in dataclasses.fields(cls)}
        unknown = set(d) - known
        if unknown:
            raise ValueError(f"unknown config keys {sorted(unknown)}")
        for k, typ in nested.items():
            if k in d and isinstance(d[k], dict):
                sub_known = {f.name for f in dataclasses.fields(typ)}
                bad = set(d[k]) - sub_known
                if bad:
                    raise ValueError(f"unknown {k} config keys {sorted(bad)}")
                d[k] = typ(**d[k])
        return cls(**d).validate()

    @classmethod
    def load(cls, path: str | Path) -> "TrainConfig":
        return cls.from_dict(json.loads(Path(path).read_text()))


def build_dataclass(cls, values: dict):
    """``cls(**values)`` after turning JSON lists/maps back into the tuple and
    nested-dataclass fields of ``cls`` (the resolved config is JSON)."""
    out = {}
    by_name = {f.name: f for f in dataclasses.fields(cls)}
    unknown = set(values) - set(by_name)
    if unknown:
        raise ValueError(f"unknown {cls.__name__} keys {sorted(unknown)}")
    for name, v in values.items():
        f = by_name[name]
        default = f.default if f.default is not dataclasses.MISSING else (
            f.default_factory() if f.default_factory is not dataclasses.MISSING else None)
        if dataclasses.is_dataclass(default) and isinstance(v, dict):
            v = build_dataclass(type(default), v)
        elif isinstance(default, tuple) and isinstance(v, list):
            v = tuple(v)
        out[name] = v
    return cls(**out)


def _json_default(o):
    if isinstance(o, (tuple, set)):
        return list(o)
    if dataclasses.is_dataclass(o):
        return dataclasses.asdict(o)
    if hasattr(o, "tolist"):
        return o.tolist()
    return str(o)
