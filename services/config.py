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
import hashlib
import json
import secrets
import time
from dataclasses import dataclass, field
from pathlib import Path

from common.algos.config import AlgoConfig
from common.algos.registry import ALL_METHODS
from common.config_fields import bounded, check_fields, coerce, from_mapping, loads_json, parse_value, type_hints
from common.env.config import EnvConfig
from common.env.scenarios import SCENARIOS
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

    mode: str = bounded("peer", choices=("peer", "client"))
    connect: list[str] = field(default_factory=list)   # e.g. ["tcp/10.0.0.1:7447"] (a router)
    listen: list[str] = field(default_factory=list)    # e.g. ["tcp/127.0.0.1:0"]
    tls_root_ca: str = ""        # CA certificate the router's certificate must chain to
    tls_cert: str = ""           # this process's certificate, e.g. "certs/{role}.pem"
    tls_key: str = ""            # its private key, e.g. "certs/{role}.key"
    tls_verify_name: bool = True  # the router's certificate must name the host in the endpoint
    # Largest message a Zenoh link of this run accepts (transport/link/rx/max_message_size,
    # on every session and the run's router) and services decode; 0 = the run's own bound
    # (TrainConfig.message_bytes_bound: its largest chunk, from T, K and M)
    max_message_bytes: int = bounded(0, ge=0, le=2**31 - 1)

    def validate(self, prefix: str = "transport.") -> None:
        check_fields(self, prefix)


@dataclass
class PortsConfig:
    """Prometheus ports; 0 disables. Actor ``i`` uses ``actor_base + i``."""

    learner: int = bounded(0, ge=0, le=65535)
    shield: int = bounded(0, ge=0, le=65535)
    actor_base: int = bounded(0, ge=0, le=65535)
    inprocess: int = bounded(0, ge=0, le=65535)   # the single registry of `sage train --mode inprocess`
    bind: str = "127.0.0.1"   # address the metric servers listen on; "0.0.0.0" for remote scrapers

    def validate(self, prefix: str = "ports.") -> None:
        check_fields(self, prefix)


@dataclass
class ShieldConfig:
    max_batch: int = bounded(256, ge=1, le=65536)        # QP rows per solve_cbf_qp call
    # wait at most this long for more requests once one arrived (longer only delays every actor)
    window_s: float = bounded(0.002, ge=0.0, le=60.0)
    # common.shield.qp.BACKENDS names (listed here so the config does not import the numba kernels;
    # tests/test_config.py keeps the two equal)
    backend: str = bounded("default", choices=("default", "dual_active_set", "osqp"))
    # Queries waiting for a batch, at most (one per actor per step is the normal load;
    # beyond this a flood is answered "overloaded" at once and counted, memory stays bounded)
    max_queue: int = bounded(1024, ge=1, le=65536)
    # Decoded queries one sender may have waiting (a pipelined actor has 2 out per
    # step); beyond it that sender's query is answered "overloaded" and counted, so
    # one flooding sender cannot take the others' turns (service is round-robin)
    max_pending_per_sender: int = bounded(4, ge=1, le=1024)

    def validate(self, prefix: str = "shield.") -> None:
        check_fields(self, prefix)


@dataclass
class ActorConfig:
    # one query; no answer -> retry (nothing executed). At most 10 min: a longer wait is a dead shield.
    shield_timeout_s: float = bounded(1.0, gt=0.0, le=600.0)
    # An answer executes only if it passes the actor's own check (common/shield/verify.py):
    # rows met to this tolerance (relative to max(1, ||C_i||)), box, human block untouched.
    # The exact QP meets rows to 1e-10; 1e-6 leaves room for float64 round-off only,
    # and above 1e-3 (a millimetre on a metre-scaled row) the check would no longer certify safety.
    verify_tol: float = bounded(1e-6, gt=0.0, le=1e-3)
    # Shield queries carry only the rows the action box does not satisfy everywhere
    # (common/shield/prune.py: exact, a dropped row can never be active or violated);
    # most wall rows are far from binding, and the rows are most of a query's bytes.
    prune_rows: bool = True
    # Parameter fencing (services/actor/service.py _fence): a params message may be at
    # most this many versions above the newest version the learner's heartbeats vouch
    # for (one update = one version; heartbeats come every status_period_s)
    max_version_step: int = bounded(64, ge=1, le=10**6)
    unhealthy_after_s: float = bounded(10.0, gt=0.0, le=3600.0)   # no shield answer this long -> "unhealthy"
    exit_on_unhealthy: bool = False    # supervised mode: exit(3) so the supervisor sees it
    params_wait_s: float = bounded(60.0, gt=0.0, le=86400.0)    # max wait for the first parameters
    # Pacing (bounded staleness at the source): an actor starts a new chunk only
    # while fewer than this many of its chunks were rolled out with its current
    # parameter version (1 = synchronous on-policy, 2 = one chunk of overlap) and
    # fewer than this many are unsettled at the learner (sent but not yet used or
    # dropped, from the backlog the learner broadcasts with its parameters).
    # Without the first rule actors outrun a slow learner and most chunks go stale;
    # without the second, a learner slower than its actors drops chunks as stale,
    # rolled out on cores the learner needed (docs/scaling.md).
    max_chunks_ahead: int = bounded(2, ge=1, le=1024)
    pace_timeout_s: float = bounded(120.0, gt=0.0, le=86400.0)   # a lost params message never deadlocks
    # Fault injection (as RLlib's fault-injecting env): per env step, the actor process
    # exits abruptly with this probability. For supervised runs, which restart it; 0 = off.
    chaos_crash_prob: float = bounded(0.0, ge=0.0, lt=1.0)
    # Double-buffered sampling (as Sample Factory's): the K envs are two groups
    # that alternate, so one group's query is at the shield while the other group
    # steps physics. Same chunks, same fail-closed rules; only the order of waiting
    # changes. Needs K >= 2 and a shielded method. Off by default: it doubles the
    # per-step calls and queries, which costs more CPU than the wait it hides where
    # actor, shield and learner share the cores (docs/scaling.md); turn it on where
    # the shield's round trip is long against a step and the actor has its cores.
    pipeline: bool = False
    # Live decision stream (`sage watch RUN`): every this many steps the actor
    # publishes the step's leaves, predicate paths and QP correction norms on
    # sage/<run>/trace/<actor>. 0 = off; 10 costs one small message per 10 steps.
    trace_every: int = bounded(0, ge=0, le=1_000_000)

    def validate(self, prefix: str = "actor.") -> None:
        check_fields(self, prefix)


# Resource bounds of a run (memory and message sizes grow with their product):
MAX_SAMPLES_PER_CHUNK = 1 << 18     # K x T of one actor's chunk (a chunk is one wire message)
UNLIMITED_UPDATES = 10**9   # a wall-clock budget alone (>= common.status.UNBOUNDED_UPDATES: shown without a budget)


@dataclass
class TrainConfig:
    run_id: str = bounded("", help="run id (default: a fresh timestamped one)")
    scenario: str = bounded("narrow_gate", choices=sorted(SCENARIOS), help="scenario")
    method: str = bounded("sage", choices=ALL_METHODS, help="method (common/algos/registry.py)")
    actors: int = bounded(1, ge=1, le=1024, help="rollout actors")
    # Shield shards: actor i asks shard i % shields on its own key (sage/<run>/shield/<k>),
    # so one shield process stops being the bottleneck once actors outgrow it
    # (docs/scaling.md). One shard serves a few actors at the training batch size.
    shields: int = bounded(1, ge=1, le=256, help="shield shards; actor i asks shard i %% shields")
    # K x T = 1024 samples per update (docs/results_narrow_gate.md)
    envs_per_actor: int = bounded(32, ge=1, le=4096, help="K: envs stepped together by one actor")
    chunk_len: int = bounded(32, ge=1, le=4096, help="T: env steps per trajectory chunk")
    chunks_per_update: int = bounded(0, ge=0, le=4096)   # 0 -> one chunk per actor
    updates: int = bounded(100, ge=1, le=UNLIMITED_UPDATES,
                           help="budget in learner updates (unlimited when only --minutes is given)")
    minutes: float | None = bounded(None, gt=0.0, le=525_600.0, help="wall-clock budget (whichever first)")
    max_lag: int = bounded(1, ge=0, le=1000, help="accept chunks from versions >= current - max_lag")
    # A chunk whose sequence number is more than this many ahead of its actor's
    # last one is refused ("seq_jump") rather than counting the gap as lost: a
    # learner down for minutes misses far fewer (actors pace on its parameters)
    max_seq_gap: int = bounded(4096, ge=1, le=2**31 - 1)
    # bound of the learner's chunk queue and pending set (drops counted)
    learner_queue_chunks: int = bounded(64, ge=1, le=4096)
    seed: int = bounded(0, ge=0, le=2**31 - 1, help="run seed (envs, trees, layouts)")
    run_dir: str = bounded("", help="run directory (default: runs/<run id>)")
    mode: str = bounded("inprocess", choices=("inprocess", "supervised"))
    checkpoint_every: int = bounded(5, ge=1, le=10**6)    # updates between checkpoints (and at the end)
    checkpoint_keep: int = bounded(3, ge=0, le=10**4)
    resume: bool = True                # learner resumes from run_dir/checkpoints if present
    status_period_s: float = bounded(1.0, gt=0.0, le=3600.0)
    params_rebroadcast_s: float = bounded(0.5, gt=0.0, le=3600.0)
    eval_episodes: int = bounded(4, ge=0, le=100_000, help="final deterministic deployment eval episodes")
    eval_max_steps: int = bounded(0, ge=0, le=10**6)       # 0 -> env default episode length
    # The final evaluation runs on each of the last this many checkpoints (eval_episodes
    # each) and reports their mean: one checkpoint's SR moves with where training happened
    # to stop (docs/protocol/table1.toml uses 3). Needs checkpoint_keep >= it.
    eval_checkpoints: int = bounded(1, ge=1, le=100)
    # Deployment probe during training: every this many updates the learner runs
    # the deterministic trees (+ exact QP when shielded) on a few held-out episodes
    # and logs deploy_sr & co. The stochastic training SR can hide a deterministic
    # policy that stalls.
    deploy_probe_every: int = bounded(20, ge=0, le=10**6)   # 0 = off
    deploy_probe_episodes: int = bounded(8, ge=1, le=10_000)
    # torch intra-op threads of the learner (0 = torch's default). On 2 cores a
    # second torch thread fights the actor/shield threads (docs/scaling.md).
    torch_threads: int = bounded(1, ge=0, le=1024)
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
            self.env = from_mapping(EnvConfig, {**self.env, "scenario": self.scenario}, "env.")
        if isinstance(self.algo, dict):
            self.algo = from_mapping(AlgoConfig, {**self.algo, "seed": self.seed}, "algo.")

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
        """Each section's own checks (types, finiteness, ranges: ``check_fields``),
        then the rules that tie fields of different sections together."""
        check_fields(self)   # this section's plain fields and transport/ports/shield/actor
        for section in (self.transport, self.ports, self.shield, self.actor):
            section.validate()
        self.env_config().validate("env.")
        self.algo_config().validate("algo.")
        check_id(self.run_id, "run id")
        if self.envs_per_actor * self.chunk_len > MAX_SAMPLES_PER_CHUNK:
            raise ValueError(f"envs_per_actor x chunk_len = {self.envs_per_actor * self.chunk_len} samples per chunk "
                             f"is over the {MAX_SAMPLES_PER_CHUNK} one chunk message may carry")
        if self.checkpoint_keep and self.eval_checkpoints > self.checkpoint_keep:
            raise ValueError(f"eval_checkpoints ({self.eval_checkpoints}) needs checkpoint_keep >= it "
                             f"(got {self.checkpoint_keep}; 0 keeps all)")
        if self.actor.chaos_crash_prob > 0 and self.mode != "supervised":
            raise ValueError("actor.chaos_crash_prob needs --mode supervised (a crashed thread is not restarted)")
        if self.shields > self.actors:
            raise ValueError(f"shields ({self.shields}) must be <= actors ({self.actors}): a shard without actors idles")
        if self.ports.shield and self.ports.actor_base and self.ports.shield < self.ports.actor_base \
                < self.ports.shield + self.shields:
            raise ValueError(f"shield shard metric ports {self.ports.shield}..{self.ports.shield + self.shields - 1} "
                             f"overlap the actors' from {self.ports.actor_base}")
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

    def set(self, path: str, value) -> None:
        """Set the field at ``path`` (``seed``, ``train.seed``, ``actor.shield_timeout_s``,
        ``env.max_steps``, ``env.reward.drop``) to ``value`` coerced to its type;
        unknown paths and ill-typed values are a ``ValueError`` naming the path.
        Ranges are checked by ``validate`` (``resolve``) once all values are in."""
        chain, keys, hint = self._locate(path)
        value = coerce(value, hint, ".".join(keys))
        key = keys[-1]
        # a frozen section (env.reward) is replaced whole, with the one field changed
        for depth in range(len(chain) - 1, -1, -1):
            node = chain[depth]
            if not type(node).__dataclass_params__.frozen:
                setattr(node, key, value)
                break
            value, key = dataclasses.replace(node, **{key: value}), keys[depth - 1]

    def set_text(self, path: str, raw: str) -> None:
        """``set`` from command-line text: JSON first (``1e-3``, ``true``, ``null``,
        ``[0.05, 1]``), else the text itself for a string field."""
        _, keys, hint = self._locate(path)
        self.set(path, parse_value(raw, hint, ".".join(keys)))

    def _locate(self, path: str):
        """(the sections from this config down to the field's owner, the field's path as
        keys without a leading ``train``, its type hint) of a dotted ``path``."""
        keys = path.split(".")
        if keys[0] == "train":
            keys = keys[1:]
        if keys in (["env", "scenario"], ["algo", "seed"]):
            raise ValueError(f"{path} follows the run's own {keys[-1]!r} field; set that instead")
        chain = [self]
        for name in keys[:-1]:
            child = getattr(chain[-1], name, None) if name in _field_names(chain[-1]) else None
            if not dataclasses.is_dataclass(child):
                raise ValueError(f"unknown config field {path!r}")
            chain.append(child)
        owner, key = chain[-1], keys[-1]
        if key not in _field_names(owner) or dataclasses.is_dataclass(getattr(owner, key)):
            where = ".".join(keys[:-1]) or "train"
            raise ValueError(f"unknown config field {path!r} ({where} has {', '.join(sorted(_field_names(owner)))})")
        return chain, keys, type_hints(type(owner))[key]

    def override(self, section: str, key: str, value) -> None:
        """Set ``env.KEY`` or ``algo.KEY`` (``set`` with the section named apart)."""
        self.set(f"{section}.{key}", value)

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

    def fingerprint(self) -> str:
        """A hash of everything that decides what the run computes: the resolved config
        without where it is written or how it is watched (run id and dir, ports,
        endpoints, certificates, logging cadence)."""
        d = dataclasses.asdict(self)
        for key in _NOT_IN_FINGERPRINT:
            d.pop(key, None)
        text = json.dumps(d, sort_keys=True, default=_json_default, separators=(",", ":"))
        return hashlib.sha256(text.encode()).hexdigest()[:16]

    def save(self, path: str | Path) -> Path:
        """Atomically: other processes (services, `sage eval`) read it back."""
        return atomic_write_text(path, self.to_json() + "\n")

    @classmethod
    def from_dict(cls, d: dict) -> "TrainConfig":
        if not isinstance(d, dict):
            raise ValueError(f"a run config is a JSON object, got {type(d).__name__}")
        return from_mapping(cls, d).validate()

    @classmethod
    def load(cls, path: str | Path) -> "TrainConfig":
        return cls.from_dict(loads_json(Path(path).read_text()))


# Where a run is written and how it is watched: not part of what it computes.
_NOT_IN_FINGERPRINT = ("run_id", "run_dir", "transport", "ports", "status_period_s", "tensorboard")


def _field_names(obj) -> set[str]:
    return {f.name for f in dataclasses.fields(obj)}


def _json_default(o):
    if isinstance(o, (tuple, set)):
        return list(o)
    if dataclasses.is_dataclass(o):
        return dataclasses.asdict(o)
    if hasattr(o, "tolist"):
        return o.tolist()
    return str(o)
