"""SAGE wire format: msgpack envelopes with typed numpy arrays (docs/wire.md).

Every message is one msgpack map

    {"v": SCHEMA_VERSION, "kind": str, "run": run_id, "sender": str,
     "seq": int, "t": float (unix seconds), "body": {...}}

and every numpy array inside ``body`` is a map
``{"nd": dtype, "shape": [...], "data": raw little-endian bytes}`` with the
dtype from ``ALLOWED_DTYPES``. Nothing is ever pickled.

``decode`` validates the envelope, then the body against the schema of its
kind: required fields, Python types, array dtype categories, ranks, fixed
sizes, leading dimensions that must agree across fields (named symbols such
as ``T`` and ``K``), and finiteness of every float. Any violation raises
``WireError(reason, detail)``; the reason codes are the ``REASONS`` tuple and
are what services count in ``sage_messages_rejected_total{reason=...}``.
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass
from typing import Any

import msgpack
import numpy as np

from common.spec import JOINT_ACT_DIM, N_CARRIERS

SCHEMA_VERSION = 1

# dtype allow-list: name on the wire -> numpy dtype (always little-endian).
ALLOWED_DTYPES = {
    "f4": np.dtype("<f4"),
    "f8": np.dtype("<f8"),
    "i4": np.dtype("<i4"),
    "i8": np.dtype("<i8"),
    "u1": np.dtype("u1"),
    "b1": np.dtype("?"),
}
_WIRE_NAME = {dt: name for name, dt in ALLOWED_DTYPES.items()}
# dtype categories a schema may ask for
_CATEGORY = {"f4": "float", "f8": "float", "i4": "int", "i8": "int", "u1": "int", "b1": "bool"}

MAX_MESSAGE_BYTES = 64 * 1024 * 1024  # one trajectory chunk is ~1 MB; refuse absurd sizes
MAX_ARRAY_RANK = 6

REASONS = (
    "malformed",       # not msgpack / truncated / trailing bytes / too large
    "envelope",        # envelope is not a map or lacks/mistypes a header field
    "version",         # schema version differs from SCHEMA_VERSION
    "run_id",          # message belongs to another run
    "kind",            # unknown kind, or not the kind this endpoint expects
    "missing_field",   # required body field absent
    "unknown_field",   # body field not in the schema
    "type",            # wrong Python type (e.g. str where an int is expected)
    "dtype",           # array dtype not allowed or wrong category
    "shape",           # wrong rank, fixed size or inconsistent leading dims
    "nonfinite",       # NaN or Inf in a float field
)


class WireError(ValueError):
    """A message failed to decode or validate; ``reason`` is one of ``REASONS``."""

    def __init__(self, reason: str, detail: str = ""):
        assert reason in REASONS, reason
        super().__init__(f"{reason}: {detail}" if detail else reason)
        self.reason = reason
        self.detail = detail


# --------------------------------------------------------------------------- schema
@dataclass(frozen=True)
class Arr:
    """Array field: dtype category and shape spec.

    ``shape`` entries are ints (fixed size), strings (symbols that must take
    the same value in every field of one message), or None (free). ``send``
    is the dtype (an ``ALLOWED_DTYPES`` name) our own senders use; a decoder
    accepts any dtype of the category.
    """

    category: str  # "float" | "int" | "bool"
    shape: tuple
    send: str = ""

    @property
    def send_dtype(self) -> np.dtype:
        return ALLOWED_DTYPES[self.send or {"float": "f8", "int": "i8", "bool": "b1"}[self.category]]


@dataclass(frozen=True)
class Scalar:
    type: str  # "int" | "float" | "str" | "bool"
    optional: bool = False


@dataclass(frozen=True)
class ArrDict:
    """Map of str -> float array of any shape (tree parameters)."""


@dataclass(frozen=True)
class FloatDict:
    """Map of str -> finite float or int (settings, diagnostics)."""


@dataclass(frozen=True)
class EpisodeList:
    """List of maps str -> finite number (finished-episode metrics)."""



SCHEMAS: dict[str, dict[str, Any]] = {
    # Actor -> learner, on sage/<run>/traj/<actor_id>. Leading [T, K] = (time, env).
    "traj": {
        "actor_id": Scalar("int"),
        "version": Scalar("int"),            # oldest parameter version used in the chunk
        "incarnation": Scalar("str"),        # learner incarnation that issued those params
        "env_steps": Scalar("int"),          # actor's cumulative env steps (all K envs)
        "version_t": Arr("int", ("T",)),     # parameter version used at each step
        # observations and states travel as float32 (what the trees and the critic read)
        "obs": Arr("float", ("T", "K", N_CARRIERS, "O"), send="f4"),
        "state": Arr("float", ("T", "K", "S"), send="f4"),
        "C": Arr("float", ("T", "K", "M", JOINT_ACT_DIM)),
        "c": Arr("float", ("T", "K", "M")),
        "row_mask": Arr("bool", ("T", "K", "M")),
        "fixed_mask": Arr("bool", ("T", "K", JOINT_ACT_DIM)),
        "a_st": Arr("float", ("T", "K", JOINT_ACT_DIM)),
        "a_bar": Arr("float", ("T", "K", JOINT_ACT_DIM)),
        "a_prop": Arr("float", ("T", "K", JOINT_ACT_DIM)),
        "a_exec": Arr("float", ("T", "K", JOINT_ACT_DIM)),
        "logp": Arr("float", ("T", "K", N_CARRIERS)),
        "leaf": Arr("int", ("T", "K", N_CARRIERS)),
        "reward": Arr("float", ("T", "K")),
        "terminated": Arr("bool", ("T", "K")),
        "truncated": Arr("bool", ("T", "K")),
        "final_state": Arr("float", ("T", "K", "S"), send="f4"),
        "final_obs": Arr("float", ("T", "K", N_CARRIERS, "O"), send="f4"),
        "last_state": Arr("float", ("K", "S"), send="f4"),
        "last_obs": Arr("float", ("K", N_CARRIERS, "O"), send="f4"),
        "episodes": EpisodeList(),
    },
    # Learner -> actors, on sage/<run>/params (re-broadcast periodically).
    "params": {
        "version": Scalar("int"),
        "incarnation": Scalar("str"),
        "method": Scalar("str"),
        "params": ArrDict(),
        "settings": FloatDict(),             # Method.actor_settings: kappa, tau, ...
    },
    # Actor -> shield query payload on sage/<run>/shield (one batched request per step).
    "shield_req": {
        "a_prop": Arr("float", ("B", JOINT_ACT_DIM)),
        "C": Arr("float", ("B", "M", JOINT_ACT_DIM)),
        "c": Arr("float", ("B", "M")),
        "row_mask": Arr("bool", ("B", "M")),
        "fixed_mask": Arr("bool", ("B", JOINT_ACT_DIM)),
    },
    # Shield -> actor reply.
    "shield_rep": {
        "a_exec": Arr("float", ("B", JOINT_ACT_DIM)),
        "status": Arr("int", ("B",)),
        "correction_norm": Arr("float", ("B",)),
        "slack": Arr("float", ("B",)),
        "batch_size": Scalar("int"),         # rows in the micro-batch this request rode in
        "solve_s": Scalar("float"),          # wall time of that solve_cbf_qp call
    },
    # Heartbeat, every service, on sage/<run>/status/<role>/<id>.
    "status": {
        "role": Scalar("str"),               # shield | actor | learner
        "id": Scalar("str"),
        "state": Scalar("str"),              # see STATUS_STATES
        "pid": Scalar("int"),
        "uptime_s": Scalar("float"),
        "version": Scalar("int"),            # newest parameter version held/published; -1 none
        "env_steps": Scalar("int"),
        "env_steps_per_s": Scalar("float"),
        "updates": Scalar("int"),
        "success_rate": Scalar("float", optional=True),   # recent episodes; None if none yet
        "shield_p99_s": Scalar("float", optional=True),   # shield: solve; actor: round trip
        "message": Scalar("str"),
        "extra": FloatDict(),
    },
    # Anyone -> all services on sage/<run>/control.
    "control": {
        "command": Scalar("str"),            # see CONTROL_COMMANDS
        "target": Scalar("str"),             # "*" or "<role>" or "<role>/<id>"
    },
}

# The per-step fields of a trajectory chunk (leading [T, K]), in schema order:
# what an actor stacks per step and the learner's batch layout (docs/interfaces.md).
TRAJ_STEP_FIELDS: tuple[str, ...] = tuple(
    k for k, spec in SCHEMAS["traj"].items() if isinstance(spec, Arr) and spec.shape[:2] == ("T", "K"))

STATUS_STATES = ("starting", "waiting", "running", "unhealthy", "stopping", "stopped", "done")
CONTROL_COMMANDS = ("stop",)


# --------------------------------------------------------------------------- encode
def _enc_array(a: np.ndarray) -> dict:
    a = np.asarray(a)
    dt = a.dtype.newbyteorder("<") if a.dtype.byteorder == ">" else a.dtype
    name = _WIRE_NAME.get(dt)
    if name is None:
        raise TypeError(f"dtype {a.dtype} not in wire allow-list {sorted(ALLOWED_DTYPES)}")
    a = np.asarray(a, dtype=ALLOWED_DTYPES[name], order="C")  # keeps 0-d arrays 0-d
    return {"nd": name, "shape": list(a.shape), "data": a.tobytes()}


def _enc_value(v):
    if isinstance(v, np.ndarray):
        return _enc_array(v)
    if isinstance(v, np.generic):
        return v.item()
    if isinstance(v, dict):
        return {str(k): _enc_value(x) for k, x in v.items()}
    if isinstance(v, (list, tuple)):
        return [_enc_value(x) for x in v]
    return v


def encode(kind: str, body: dict, *, run_id: str, sender: str, seq: int) -> bytes:
    """Serialize one message. Raises TypeError/ValueError on a programming error
    (unknown kind, array dtype outside the allow-list)."""
    if kind not in SCHEMAS:
        raise ValueError(f"unknown message kind {kind!r}")
    env = {
        "v": SCHEMA_VERSION,
        "kind": kind,
        "run": str(run_id),
        "sender": str(sender),
        "seq": int(seq),
        "t": time.time(),
        "body": _enc_value(body),
    }
    return msgpack.packb(env, use_bin_type=True)


# --------------------------------------------------------------------------- decode
@dataclass
class Message:
    kind: str
    run_id: str
    sender: str
    seq: int
    t: float
    body: dict


def _dec_array(name: str, v) -> np.ndarray:
    if not isinstance(v, dict) or set(v) != {"nd", "shape", "data"}:
        raise WireError("type", f"{name}: expected an array map")
    dt = ALLOWED_DTYPES.get(v["nd"]) if isinstance(v["nd"], str) else None
    if dt is None:
        raise WireError("dtype", f"{name}: dtype {v['nd']!r} not allowed")
    shape = v["shape"]
    if (not isinstance(shape, list) or len(shape) > MAX_ARRAY_RANK
            or not all(isinstance(s, int) and not isinstance(s, bool) and s >= 0 for s in shape)):
        raise WireError("shape", f"{name}: bad shape {shape!r}")
    data = v["data"]
    if not isinstance(data, bytes):
        raise WireError("type", f"{name}: data is not bytes")
    if len(data) != math.prod(shape) * dt.itemsize:
        raise WireError("shape", f"{name}: {len(data)} bytes for shape {shape} {v['nd']}")
    # copy: frombuffer views are read-only and pin the message buffer
    arr = np.frombuffer(data, dtype=dt).reshape(shape).copy()
    if dt == np.dtype("?") and arr.view(np.uint8).max(initial=0) > 1:
        raise WireError("dtype", f"{name}: bool bytes other than 0/1")
    return arr


def _check_number(name: str, v, typ: str, optional: bool):
    if v is None:
        if optional:
            return None
        raise WireError("type", f"{name}: null")
    if typ == "int":
        if not isinstance(v, int) or isinstance(v, bool):
            raise WireError("type", f"{name}: expected int, got {type(v).__name__}")
        return v
    if typ == "float":
        if not isinstance(v, (int, float)) or isinstance(v, bool):
            raise WireError("type", f"{name}: expected float, got {type(v).__name__}")
        if not math.isfinite(v):
            raise WireError("nonfinite", name)
        return float(v)
    if typ == "str":
        if not isinstance(v, str):
            raise WireError("type", f"{name}: expected str, got {type(v).__name__}")
        return v
    if typ == "bool":
        if not isinstance(v, bool):
            raise WireError("type", f"{name}: expected bool")
        return v
    raise AssertionError(typ)


def _check_float_map(name: str, v) -> dict:
    if not isinstance(v, dict):
        raise WireError("type", f"{name}: expected a map")
    out = {}
    for k, x in v.items():
        if not isinstance(k, str):
            raise WireError("type", f"{name}: non-str key")
        if isinstance(x, bool):
            out[k] = float(x)
            continue
        out[k] = _check_number(f"{name}.{k}", x, "float", optional=False)
    return out


def _validate_body(kind: str, body) -> dict:
    if not isinstance(body, dict):
        raise WireError("envelope", "body is not a map")
    schema = SCHEMAS[kind]
    extra = set(body) - set(schema)
    if extra:
        raise WireError("unknown_field", f"{kind}: {sorted(map(str, extra))}")
    out: dict[str, Any] = {}
    dims: dict[str, tuple[int, str]] = {}  # symbol -> (size, first field that bound it)
    for name, spec in schema.items():
        if name not in body:
            if isinstance(spec, Scalar) and spec.optional:
                out[name] = None
                continue
            raise WireError("missing_field", f"{kind}.{name}")
        v = body[name]
        if isinstance(spec, Scalar):
            out[name] = _check_number(name, v, spec.type, spec.optional)
        elif isinstance(spec, FloatDict):
            out[name] = _check_float_map(name, v)
        elif isinstance(spec, EpisodeList):
            if not isinstance(v, list):
                raise WireError("type", f"{name}: expected a list")
            out[name] = [_check_float_map(f"{name}[{i}]", e) for i, e in enumerate(v)]
        elif isinstance(spec, ArrDict):
            if not isinstance(v, dict) or not all(isinstance(k, str) for k in v):
                raise WireError("type", f"{name}: expected a map of arrays")
            arrs = {}
            for k, x in v.items():
                a = _dec_array(f"{name}.{k}", x)
                if a.dtype.kind == "f" and not np.isfinite(a).all():
                    raise WireError("nonfinite", f"{name}.{k}")
                arrs[k] = a
            out[name] = arrs
        elif isinstance(spec, Arr):
            a = _dec_array(name, v)
            cat = _CATEGORY[_WIRE_NAME[a.dtype]]
            if cat != spec.category:
                raise WireError("dtype", f"{name}: {cat} array where {spec.category} expected")
            if a.ndim != len(spec.shape):
                raise WireError("shape", f"{name}: rank {a.ndim}, expected {len(spec.shape)}")
            for axis, (want, got) in enumerate(zip(spec.shape, a.shape)):
                if isinstance(want, int) and got != want:
                    raise WireError("shape", f"{name}: axis {axis} is {got}, expected {want}")
                if isinstance(want, str):
                    if want in dims and dims[want][0] != got:
                        raise WireError(
                            "shape", f"{name}: {want}={got} but {dims[want][1]} has {want}={dims[want][0]}")
                    dims.setdefault(want, (got, name))
            if cat == "float" and not np.isfinite(a).all():
                raise WireError("nonfinite", name)
            out[name] = a
        else:  # pragma: no cover - schema typo
            raise AssertionError(spec)
    return out


def decode(payload: bytes, *, run_id: str, expect: str | tuple[str, ...] | None = None) -> Message:
    """Parse and validate one message; raise ``WireError`` on anything wrong.

    ``run_id`` must match the envelope (runs never cross-talk even if keys are
    misrouted); ``expect`` restricts the accepted kind(s).
    """
    if not isinstance(payload, (bytes, bytearray, memoryview)):
        raise WireError("malformed", "payload is not bytes")
    if len(payload) > MAX_MESSAGE_BYTES:
        raise WireError("malformed", f"{len(payload)} bytes > {MAX_MESSAGE_BYTES}")
    try:
        env = msgpack.unpackb(bytes(payload), raw=False, strict_map_key=True,
                              use_list=True, max_bin_len=MAX_MESSAGE_BYTES)
    except Exception as exc:  # truncated, trailing bytes, invalid utf-8, ...
        raise WireError("malformed", f"{type(exc).__name__}: {exc}") from None
    if not isinstance(env, dict):
        raise WireError("envelope", "not a map")
    # version first: a future schema may change every other header field
    if "v" not in env:
        raise WireError("envelope", "no schema version")
    if env["v"] != SCHEMA_VERSION:
        raise WireError("version", f"got {env['v']!r}, expected {SCHEMA_VERSION}")
    for key, typ in (("kind", str), ("run", str), ("sender", str), ("seq", int), ("t", (int, float))):
        if key not in env or not isinstance(env[key], typ) or isinstance(env[key], bool):
            raise WireError("envelope", f"header field {key!r}")
    if set(env) != {"v", "kind", "run", "sender", "seq", "t", "body"}:
        raise WireError("envelope", f"header fields {sorted(env)}")
    if env["run"] != run_id:
        raise WireError("run_id", f"got {env['run']!r}, expected {run_id!r}")
    kind = env["kind"]
    if kind not in SCHEMAS:
        raise WireError("kind", f"unknown kind {kind!r}")
    if expect is not None and kind not in ((expect,) if isinstance(expect, str) else expect):
        raise WireError("kind", f"got {kind!r}, expected {expect!r}")
    body = _validate_body(kind, env["body"])
    return Message(kind=kind, run_id=env["run"], sender=env["sender"], seq=env["seq"],
                   t=float(env["t"]), body=body)


# --------------------------------------------------------------------------- helpers
def traj_batch(chunks: list[dict]) -> dict[str, np.ndarray]:
    """Concatenate decoded trajectory chunk bodies along the env axis K into
    the learner batch of docs/interfaces.md (leading [T, K]). All chunks must
    share T, S, O and M (checked)."""
    if not chunks:
        raise ValueError("no chunks")
    keys = [k for k, s in SCHEMAS["traj"].items() if isinstance(s, Arr) and k != "version_t"]
    out = {}
    for k in keys:
        axis = 0 if k in ("last_state", "last_obs") else 1
        parts = [ch[k] for ch in chunks]
        ref = parts[0].shape
        for p in parts[1:]:
            if p.ndim != len(ref) or any(a != b for i, (a, b) in enumerate(zip(p.shape, ref)) if i != axis):
                raise ValueError(f"chunk field {k}: shapes {p.shape} vs {ref} differ off the env axis")
        out[k] = np.concatenate(parts, axis=axis)
    return out
