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
as ``T`` and ``K``), finiteness of every float, value ranges (ids, versions,
counters, ``seq`` non-negative) and enums (``status.state``,
``control.command``). Any violation raises ``WireError(reason, detail)``;
the reason codes are the ``REASONS`` tuple and are what services count in
``sage_messages_rejected_total{reason=...}``.

Decoding is bounded before it allocates (the ``MAX_*`` limits below): the
payload size, every msgpack str/bin/ext/array/map length, the number of
array/map entries of the whole message (counted while unpacking, which stops
at the limit), the nesting depth, and every array's dimensions (checked before
any byte size is computed). ``decode`` raises nothing but ``WireError``, for
any input bytes.
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
# Resource limits (reason "limit"), all checked before the allocation they bound.
# Valid messages are far inside them: a traj chunk (T=K=32) has ~200 entries,
# depth 5 (envelope > body > params > array map > shape) and arrays < 2**20.
MAX_ARRAY_DIM = 2**31 - 1     # each array dimension
MAX_ARRAY_ELEMENTS = 2**26    # product of an array's non-zero dimensions (zero-size arrays too)
MAX_CONTAINER_LEN = 2**16     # entries of one msgpack array or map (checked at its header)
MAX_ITEMS = 2**18             # entries of all arrays and maps of one message together
MAX_DEPTH = 8                 # nesting of arrays/maps (the parser itself stops at 1024)
MAX_STR_BYTES = 2**16         # one msgpack str
MAX_EXT_BYTES = 16            # one msgpack ext (never valid here; a timestamp is <= 12)
MAX_NAME_LEN = 256            # run id, sender, ids, incarnation, method, map keys, ...
MAX_TEXT_LEN = 4096           # free text: status.message
INT64_MIN, INT64_MAX = -2**63, 2**63 - 1  # every int scalar (msgpack also carries up to 2**64-1)

REASONS = (
    "malformed",       # not msgpack / truncated / trailing bytes / invalid utf-8
    "envelope",        # envelope is not a map or lacks/mistypes a header field
    "version",         # schema version differs from SCHEMA_VERSION
    "run_id",          # message belongs to another run
    "kind",            # unknown kind, or not the kind this endpoint expects
    "missing_field",   # required body field absent
    "unknown_field",   # body field not in the schema
    "type",            # wrong Python type (e.g. str where an int is expected)
    "dtype",           # array dtype not allowed or wrong category
    "shape",           # wrong rank, fixed size or inconsistent leading dims
    "nonfinite",       # NaN or Inf in a float field (or in the header time t)
    "value",           # right type, value out of range or not in its enum (negative version, ...)
    "limit",           # a size limit (MAX_*): payload, str/bin/array/map length, entries,
                       # nesting depth, array dimensions, string field length
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
    accepts any dtype of the category. An ``optional`` field may be absent
    (decoded as None).
    """

    category: str  # "float" | "int" | "bool"
    shape: tuple
    send: str = ""
    optional: bool = False

    @property
    def send_dtype(self) -> np.dtype:
        return ALLOWED_DTYPES[self.send or {"float": "f8", "int": "i8", "bool": "b1"}[self.category]]


@dataclass(frozen=True)
class Scalar:
    """Scalar field. ints are always within int64; ``lo`` raises the lower
    bound (0 for ids/versions/counters, -1 where -1 means "none"). strs are at
    most ``max_len`` characters and, with ``choices``, one of them."""

    type: str  # "int" | "float" | "str" | "bool"
    optional: bool = False
    lo: int | None = None
    choices: tuple[str, ...] = ()
    max_len: int = MAX_NAME_LEN


@dataclass(frozen=True)
class ArrDict:
    """Map of str -> float array of any shape (tree parameters)."""


@dataclass(frozen=True)
class FloatDict:
    """Map of str -> finite float or int (settings, diagnostics)."""


@dataclass(frozen=True)
class EpisodeList:
    """List of maps str -> finite number (finished-episode metrics)."""


STATUS_STATES = ("starting", "waiting", "running", "unhealthy", "stopping", "stopped", "done")
CONTROL_COMMANDS = ("stop",)

SCHEMAS: dict[str, dict[str, Any]] = {
    # Actor -> learner, on sage/<run>/traj/<actor_id>. Leading [T, K] = (time, env).
    "traj": {
        "actor_id": Scalar("int", lo=0),
        "version": Scalar("int", lo=0),      # oldest parameter version used in the chunk
        "incarnation": Scalar("str"),        # learner incarnation that issued those params
        "env_steps": Scalar("int", lo=0),    # actor's cumulative env steps (all K envs)
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
        # the verified shield answer's QP status per step (0 optimal, 1 infeasible:
        # minimum-violation action); -1 for an unshielded method's step
        "shield_status": Arr("int", ("T", "K"), send="i4"),
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
        "version": Scalar("int", lo=0),
        "incarnation": Scalar("str"),
        "method": Scalar("str"),
        "params": ArrDict(),
        "settings": FloatDict(),             # Method.actor_settings: kappa, tau, ...
        # Demand pacing (ActorConfig.max_chunks_ahead), per actor id: the sequence
        # number of the last chunk the learner admitted from it (-1: none) and how
        # many of its chunks wait unused. Absent from a learner that does not pace.
        "chunks_received": Arr("int", ("A",), optional=True),
        "chunks_waiting": Arr("int", ("A",), optional=True),
    },
    # Actor -> shield query payload on sage/<run>/shield/<k> (one batched request per step).
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
        "batch_size": Scalar("int", lo=0),   # rows in the micro-batch this request rode in
        "solve_s": Scalar("float"),          # wall time of that solve_cbf_qp call
    },
    # Actor -> watchers (`sage watch`), on sage/<run>/trace/<actor_id>: one step
    # in `every` of the actor's decisions (actor.trace_every), for live audits.
    "trace": {
        "actor_id": Scalar("int", lo=0),
        "version": Scalar("int", lo=0),      # parameter version the step was decided with
        "env_steps": Scalar("int", lo=0),    # actor's cumulative env steps at that step
        "every": Scalar("int", lo=1),        # thinning: this is one step in `every`
        "leaf": Arr("int", ("K", N_CARRIERS), send="i4"),            # active leaf per carrier
        "nodes": Arr("int", ("K", N_CARRIERS, "D"), send="i4"),      # predicate path: node ids, root first
        "sides": Arr("bool", ("K", N_CARRIERS, "D")),                # branch taken at each (True = w.o > b)
        "correction_norm": Arr("float", ("K",)),                     # ||a_exec - a_prop||: the QP's correction
    },
    # Heartbeat, every service, on sage/<run>/status/<role>/<id>.
    "status": {
        "role": Scalar("str"),               # shield | actor | learner
        "id": Scalar("str"),
        "state": Scalar("str", choices=STATUS_STATES),
        "pid": Scalar("int", lo=0),
        "uptime_s": Scalar("float"),
        "version": Scalar("int", lo=-1),     # newest parameter version held/published; -1 none
        "env_steps": Scalar("int", lo=0),
        "env_steps_per_s": Scalar("float"),
        "updates": Scalar("int", lo=0),
        "success_rate": Scalar("float", optional=True),   # recent episodes; None if none yet
        "shield_p99_s": Scalar("float", optional=True),   # shield: solve; actor: round trip
        "message": Scalar("str", max_len=MAX_TEXT_LEN),
        "extra": FloatDict(),
    },
    # Anyone -> all services on sage/<run>/control.
    "control": {
        "command": Scalar("str", choices=CONTROL_COMMANDS),
        "target": Scalar("str"),             # "*" or "<role>" or "<role>/<id>"
    },
}

# The per-step fields of a trajectory chunk (leading [T, K]), in schema order:
# what an actor stacks per step and the learner's batch layout (docs/interfaces.md).
TRAJ_STEP_FIELDS: tuple[str, ...] = tuple(
    k for k, spec in SCHEMAS["traj"].items() if isinstance(spec, Arr) and spec.shape[:2] == ("T", "K"))



def traj_bytes_bound(T: int, K: int, M: int, O: int, S: int) -> int:
    """An upper bound on the encoded size of a trajectory chunk of T steps of K
    envs (M rows, obs_dim O, state_dim S): every array element counted at 8
    bytes (the widest allowed dtype), up to one finished-episode map of 16
    numbers per env step, and 64 KiB for msgpack framing and the header. The
    largest message a run sends, and so the transport's limit for it."""
    dims = {"T": T, "K": K, "M": M, "O": O, "S": S}
    elements = 0
    for spec in SCHEMAS["traj"].values():
        if isinstance(spec, Arr):
            elements += math.prod(dims.get(s, s) if isinstance(s, str) else s for s in spec.shape)
    return 8 * elements + T * K * 16 * 40 + 64 * 1024


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


_HEADER = frozenset({"v", "kind", "run", "sender", "seq", "t", "body"})


def _brief(v) -> str:
    """A short description of an untrusted value for an error detail: never a
    full repr (a value may be huge, or nested deeper than repr can recurse)."""
    if v is None or isinstance(v, (bool, int, float)):
        s = repr(v)
    elif isinstance(v, (str, bytes)):
        s = repr(v[:40]) + ("..." if len(v) > 40 else "")
    elif isinstance(v, list) and len(v) <= MAX_ARRAY_RANK and all(type(x) is int for x in v):
        s = repr(v)
    elif isinstance(v, (list, dict)):
        return f"<{type(v).__name__} of {len(v)}>"
    else:
        return f"<{type(v).__name__}>"
    return s if len(s) <= 80 else s[:77] + "..."


class _TooManyItems(Exception):
    pass


def _unpack(payload: bytes):
    """msgpack.unpackb with every length bounded at its header (max_*_len)
    and the entries of all arrays and maps counted as they are built: the
    hooks run on each finished container, so a message of millions of tiny
    maps stops after MAX_ITEMS of them instead of building them all."""
    left = MAX_ITEMS

    def count(obj):
        nonlocal left
        left -= len(obj) + 1
        if left < 0:
            raise _TooManyItems
        return obj

    try:
        return msgpack.unpackb(
            payload, raw=False, strict_map_key=True, use_list=True,
            object_hook=count, list_hook=count,
            max_str_len=MAX_STR_BYTES, max_bin_len=MAX_MESSAGE_BYTES, max_ext_len=MAX_EXT_BYTES,
            max_array_len=MAX_CONTAINER_LEN, max_map_len=MAX_CONTAINER_LEN)
    except _TooManyItems:
        raise WireError("limit", f"more than {MAX_ITEMS} array/map entries") from None
    except msgpack.StackError:
        raise WireError("limit", "nested deeper than the msgpack parser allows") from None
    except Exception as exc:  # noqa: BLE001 - truncated, trailing bytes, invalid utf-8, bad ext, ...
        text = str(exc)[:200]
        if isinstance(exc, ValueError) and "exceeds max_" in text:  # "N exceeds max_map_len(M)"
            raise WireError("limit", text) from None
        raise WireError("malformed", f"{type(exc).__name__}: {text}") from None


def _check_depth(env) -> None:
    """Nesting of arrays/maps <= MAX_DEPTH (a walk over at most MAX_ITEMS entries)."""
    stack = [(env, 1)]
    while stack:
        obj, depth = stack.pop()
        if depth > MAX_DEPTH:
            raise WireError("limit", f"nested deeper than {MAX_DEPTH}")
        for x in (obj.values() if type(obj) is dict else obj):
            if type(x) is dict or type(x) is list:
                stack.append((x, depth + 1))


def _dec_array(name: str, v, spec_shape: tuple = (), bounds: dict[str, int] | None = None) -> np.ndarray:
    if not isinstance(v, dict) or set(v) != {"nd", "shape", "data"}:
        raise WireError("type", f"{name}: expected an array map")
    nd = v["nd"]
    dt = ALLOWED_DTYPES.get(nd) if isinstance(nd, str) else None
    if dt is None:
        raise WireError("dtype", f"{name}: dtype {_brief(nd)} not allowed")
    shape = v["shape"]
    if (not isinstance(shape, list) or len(shape) > MAX_ARRAY_RANK
            or not all(isinstance(s, int) and not isinstance(s, bool) and s >= 0 for s in shape)):
        raise WireError("shape", f"{name}: bad shape {_brief(shape)}")
    # Bound the dims before any size is computed. The product of the non-zero
    # dims counts: numpy refuses a shape whose non-zero dims overflow even for a
    # zero-size array (shape [0, 2**64-1] raised a plain ValueError here).
    elements = 1
    for s in shape:
        if s > MAX_ARRAY_DIM:
            raise WireError("limit", f"{name}: dimension {s} > {MAX_ARRAY_DIM}")
        elements *= max(s, 1)
    if elements > MAX_ARRAY_ELEMENTS:
        raise WireError("limit", f"{name}: shape {shape} has more than {MAX_ARRAY_ELEMENTS} elements")
    if bounds:   # the run's caps on shape symbols, before the copy below
        for want, got in zip(spec_shape, shape):
            if isinstance(want, str) and want in bounds and got > bounds[want]:
                raise WireError("limit", f"{name}: {want}={got} > {bounds[want]}, this run's bound")
    data = v["data"]
    if not isinstance(data, bytes):
        raise WireError("type", f"{name}: data is not bytes")
    if len(data) != math.prod(shape) * dt.itemsize:
        raise WireError("shape", f"{name}: {len(data)} bytes for shape {shape} {nd}")
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


def _check_scalar(name: str, v, spec: Scalar):
    """Type (``_check_number``), then range, length and enum of a scalar field."""
    v = _check_number(name, v, spec.type, spec.optional)
    if v is None:
        return None
    if spec.type == "int":
        lo = INT64_MIN if spec.lo is None else spec.lo
        if not lo <= v <= INT64_MAX:
            raise WireError("value", f"{name}: {v} outside [{lo}, {INT64_MAX}]")
    elif spec.type == "str":
        if len(v) > spec.max_len:
            raise WireError("limit", f"{name}: {len(v)} characters > {spec.max_len}")
        if spec.choices and v not in spec.choices:
            raise WireError("value", f"{name}: {_brief(v)} not one of {spec.choices}")
    return v


def _check_key(name: str, k) -> None:
    if not isinstance(k, str):
        raise WireError("type", f"{name}: non-str key")
    if len(k) > MAX_NAME_LEN:
        raise WireError("limit", f"{name}: key of {len(k)} characters > {MAX_NAME_LEN}")


def _check_float_map(name: str, v) -> dict:
    if not isinstance(v, dict):
        raise WireError("type", f"{name}: expected a map")
    out = {}
    for k, x in v.items():
        _check_key(name, k)
        if isinstance(x, bool):
            out[k] = float(x)
            continue
        out[k] = _check_number(f"{name}.{k}", x, "float", optional=False)
    return out


def _validate_body(kind: str, body, bounds: dict[str, int] | None = None) -> dict:
    if not isinstance(body, dict):
        raise WireError("envelope", "body is not a map")
    schema = SCHEMAS[kind]
    extra = set(body) - set(schema)
    if extra:
        raise WireError("unknown_field", f"{kind}: {sorted(map(_brief, extra))[:8]}")
    out: dict[str, Any] = {}
    dims: dict[str, tuple[int, str]] = {}  # symbol -> (size, first field that bound it)
    for name, spec in schema.items():
        if name not in body:
            if isinstance(spec, (Scalar, Arr)) and spec.optional:
                out[name] = None
                continue
            raise WireError("missing_field", f"{kind}.{name}")
        v = body[name]
        if isinstance(spec, Scalar):
            out[name] = _check_scalar(name, v, spec)
        elif isinstance(spec, FloatDict):
            out[name] = _check_float_map(name, v)
        elif isinstance(spec, EpisodeList):
            if not isinstance(v, list):
                raise WireError("type", f"{name}: expected a list")
            out[name] = [_check_float_map(f"{name}[{i}]", e) for i, e in enumerate(v)]
        elif isinstance(spec, ArrDict):
            if not isinstance(v, dict):
                raise WireError("type", f"{name}: expected a map of arrays")
            arrs = {}
            for k, x in v.items():
                _check_key(name, k)
                a = _dec_array(f"{name}.{k}", x)
                if a.dtype.kind == "f" and not np.isfinite(a).all():
                    raise WireError("nonfinite", f"{name}.{k}")
                arrs[k] = a
            out[name] = arrs
        elif isinstance(spec, Arr):
            a = _dec_array(name, v, spec.shape, bounds)
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


def decode(payload: bytes, *, run_id: str, expect: str | tuple[str, ...] | None = None,
           bounds: dict[str, int] | None = None, max_bytes: int = MAX_MESSAGE_BYTES) -> Message:
    """Parse and validate one message; raise ``WireError`` on anything wrong
    (and nothing else, whatever the bytes).

    ``run_id`` must match the envelope (runs never cross-talk even if keys are
    misrouted); ``expect`` restricts the accepted kind(s). ``bounds``: the
    largest size a shape symbol may take in this run (e.g. a shield request's
    ``B`` and ``M`` from the run's spec); a larger one is a ``limit``, as is
    a payload over ``max_bytes`` (a run's own bound, at most MAX_MESSAGE_BYTES).
    """
    if not isinstance(payload, (bytes, bytearray, memoryview)):
        raise WireError("malformed", "payload is not bytes")
    size = payload.nbytes if isinstance(payload, memoryview) else len(payload)
    limit = min(int(max_bytes), MAX_MESSAGE_BYTES)
    if size > limit:
        raise WireError("limit", f"{size} bytes > {limit}")
    env = _unpack(bytes(payload))
    if isinstance(env, (dict, list)):
        _check_depth(env)
    if not isinstance(env, dict):
        raise WireError("envelope", "not a map")
    # version first: a future schema may change every other header field
    if "v" not in env:
        raise WireError("envelope", "no schema version")
    if type(env["v"]) is not int or env["v"] != SCHEMA_VERSION:
        raise WireError("version", f"got {_brief(env['v'])}, expected {SCHEMA_VERSION}")
    for key, typ in (("kind", str), ("run", str), ("sender", str), ("seq", int), ("t", (int, float))):
        if key not in env or not isinstance(env[key], typ) or isinstance(env[key], bool):
            raise WireError("envelope", f"header field {key!r}")
    if set(env) != _HEADER:
        raise WireError("envelope", f"header fields: missing {sorted(_HEADER - set(env))}, "
                                    f"unknown {sorted(map(_brief, set(env) - _HEADER))[:8]}")
    for key in ("run", "sender"):
        if len(env[key]) > MAX_NAME_LEN:
            raise WireError("limit", f"header field {key!r}: {len(env[key])} characters > {MAX_NAME_LEN}")
    if not 0 <= env["seq"] <= INT64_MAX:
        raise WireError("value", f"seq {env['seq']} outside [0, {INT64_MAX}]")
    if not math.isfinite(env["t"]):
        raise WireError("nonfinite", "header field 't'")
    if env["run"] != run_id:
        raise WireError("run_id", f"got {_brief(env['run'])}, expected {run_id!r}")
    kind = env["kind"]
    if kind not in SCHEMAS:
        raise WireError("kind", f"unknown kind {_brief(kind)}")
    if expect is not None and kind not in ((expect,) if isinstance(expect, str) else expect):
        raise WireError("kind", f"got {kind!r}, expected {expect!r}")
    body = _validate_body(kind, env["body"], bounds)
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
