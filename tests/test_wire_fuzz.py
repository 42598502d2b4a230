"""Fuzzing the wire decoder (common/wire.py, docs/wire.md): whatever the bytes,
``decode`` raises nothing but ``WireError`` and its memory stays bounded.

The cases are mutations of REAL encodings of every message kind in
``wire.SCHEMAS`` (one valid body per kind, built from the schema itself so the
test follows schema changes): byte level (bit flips, special bytes, truncation,
splicing, inserted/deleted/duplicated ranges, raw msgpack headers claiming
giant str/bin/array/map/ext lengths or deep nesting) and structural (any
node of the decoded envelope replaced by an extreme value: 2**64-1, -1, NaN,
huge or zero-size shapes, deep nesting, long strings, bytes/int keys, ext
types; fields deleted or added; array maps re-shaped). Fixed seed.
"""
from __future__ import annotations

import math
import random
import resource
import time
import traceback
import tracemalloc
from collections import Counter

import msgpack
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from common import wire

RUN = "run-f"
SEED = 20240611
N_CASES = 100_000
PEAK_BOUND = 200 * 2**20      # bytes: tracemalloc peak of one decode, and max-RSS growth of the loop


# --------------------------------------------------------------------------- valid seeds
def valid_body(kind: str, sizes: dict, rng: np.random.Generator) -> dict:
    """One valid body of ``kind``, built from its schema."""
    out = {}
    for name, spec in wire.SCHEMAS[kind].items():
        if isinstance(spec, wire.Arr):
            shape = tuple(sizes[s] if isinstance(s, str) else s for s in spec.shape)
            if spec.category == "float":
                out[name] = rng.normal(size=shape).astype(spec.send_dtype)
            elif spec.category == "int":
                out[name] = rng.integers(0, 3, shape).astype(spec.send_dtype)
            else:
                out[name] = rng.random(shape) < 0.5
        elif isinstance(spec, wire.Scalar):
            if spec.choices:
                out[name] = spec.choices[0]
            else:
                out[name] = {"int": 1, "float": 0.5, "str": "x", "bool": True}[spec.type]
        elif isinstance(spec, wire.FloatDict):
            out[name] = {"a": 1.0, "b": 2}
        elif isinstance(spec, wire.EpisodeList):
            out[name] = [{"return": 1.5, "length": 30}, {"success": True}]
        elif isinstance(spec, wire.ArrDict):
            out[name] = {"carrier_0/W": rng.normal(size=(2, 3)), "b": np.arange(3, dtype=np.float32),
                         "leaf": np.arange(2, dtype=np.int32)}
        else:  # pragma: no cover - a new schema element: extend this builder
            raise TypeError(f"{kind}.{name}: {spec!r}")
    return out


def seed_payloads() -> list[bytes]:
    rng = np.random.default_rng(SEED)
    small = {s: 1 for s in "TKMOSBDA"}
    other = {"T": 2, "K": 2, "M": 0, "O": 2, "S": 3, "B": 2, "D": 3, "A": 2}   # zero-size arrays too
    out = []
    for kind in wire.SCHEMAS:
        for i, sizes in enumerate((small, other)):
            body = valid_body(kind, sizes, rng)
            if kind == "status" and i:
                body.update(success_rate=None, version=-1, state=wire.STATUS_STATES[-1])
            p = wire.encode(kind, body, run_id=RUN, sender="actor/0", seq=i)
            wire.decode(p, run_id=RUN, expect=kind)                      # the seeds are valid
            out.append(p)
    return out


SEEDS = seed_payloads()


def test_every_kind_has_a_valid_seed():
    kinds = {wire.decode(p, run_id=RUN).kind for p in SEEDS}
    assert kinds == set(wire.SCHEMAS)


# --------------------------------------------------------------------------- mutations
def _nest(n, leaf=0):
    for _ in range(n):
        leaf = [leaf]
    return leaf


def _arr(nd, shape, data=b""):
    return {"nd": nd, "shape": shape, "data": data}


EXTREMES = [
    2**64 - 1, 2**63, 2**63 - 1, -2**63, -2**31, -2, -1, 0, 1, 2, 3, 9, 2**31 - 1, 2**31, 2**32,
    math.nan, math.inf, -math.inf, -0.0, 1e308, 5e-324, 0.5,
    None, True, False,
    "", "x", "x" * 257, "é" * 4097, "\x00", "\ud7ff" * 3, "f8", "b1", "u1", "f2", "O", "<f8",
    "running", "stop", "traj", "params", "status", RUN, "run-b", "*",
    b"", b"\x00", b"\x02" * 9, b"\xff" * 72, b"\x00\x00\xc0\x7f",
    [], [0], [0] * 7, [2**64 - 1, 0], [0, 2**64 - 1], [0, 2**31, 2**31, 2**31], [2**31] * 3, [2**13] * 3,
    [3, 9], [1] * 6, [-1], [True], [1.0], [[]], list(range(300)), [{}] * 100, _nest(9), _nest(7), _nest(60),
    {}, {"a": {"b": {}}}, {1: 2}, {b"k": 1}, {"x" * 300: 1.0}, {"kappa": math.nan}, {"": None},
    _arr("f8", [0, 2**64 - 1]), _arr("f8", [2**31 - 1, 0]), _arr("f8", [0, 2**31, 2**31]),
    _arr("b1", [2], b"\x00\x02"), _arr("f8", [], b"\x00" * 8), _arr("f4", [1], b"\x00\x00\xc0\x7f"),
    _arr("i8", [1], b"\xff" * 8), _arr("f8", [2**26 + 1]), _arr("u1", [2**31 - 1], b"\x00"),
    msgpack.ExtType(1, b"abc"), msgpack.ExtType(127, b""), msgpack.Timestamp(0, 0),
]

# drawn as fresh copies (unpacked from their encoding): mutations must never alter the palette
_EXTREMES_PACKED = [msgpack.packb(v, use_bin_type=True) for v in EXTREMES]


def _extreme(rng: random.Random):
    return msgpack.unpackb(rng.choice(_EXTREMES_PACKED), raw=False, strict_map_key=False)


_PH = b"\xfe\xfd-wire-fuzz-placeholder-\xfd\xfe"
_PH_PACKED = msgpack.packb(_PH, use_bin_type=True)

# raw msgpack spliced in place of a value: headers claiming more than is there or allowed
RAW = [
    b"\xdb\xff\xff\xff\xff", b"\xdb\x7f\xff\xff\xff" + b"x" * 10, b"\xda\xff\xff" + b"x" * 3,
    b"\xc6\xff\xff\xff\xff", b"\xc6\x03\xff\xff\xff" + b"\x00" * 8, b"\xc5\xff\xff",
    b"\xdd\xff\xff\xff\xff", b"\xdd\x00\x01\x00\x01" + b"\xc0" * 10, b"\xdc\xff\xff" + b"\xc0" * 3,
    b"\xdf\xff\xff\xff\xff", b"\xdf\x00\x00\xff\xff", b"\xde\x00\x02\xa1a\xc0",
    b"\xc9\xff\xff\xff\xff\x01", b"\xc8\xff\xff\x01", b"\xc7\x05\xff" + b"\x00" * 5,
    b"\xd6\xff\x00\x00\x00\x00", b"\xd7\xff" + b"\xff" * 8, b"\xc1", b"\x91" * 1030 + b"\xc0",
    b"\x91" * 20 + b"\xc0", b"\xa2\xff\xfe", b"\xcf" + b"\xff" * 8, b"\xd3\x80" + b"\x00" * 7,
    b"\xcb\x7f\xf8" + b"\x00" * 6, b"\xca\x7f\x80\x00\x00", b"\xdc\x10\x00" + b"\x80" * 4096,
    b"\x81\xa2nd\xa2f8", b"\x83\xa2nd\xa2f8\xa5shape\x92\x00\xcf" + b"\xff" * 8 + b"\xa4data\xc4\x00",
]

SPECIAL_BYTES = [0x00, 0x7F, 0x80, 0x8F, 0x90, 0x9F, 0xA0, 0xBF, 0xC0, 0xC1, 0xC2, 0xC3, 0xC4, 0xC6, 0xC9,
                 0xCA, 0xCB, 0xCF, 0xD3, 0xD4, 0xD8, 0xDB, 0xDC, 0xDD, 0xDE, 0xDF, 0xE0, 0xFF]


def _nodes(env):
    """(parent, key) of every value under the envelope, and the array maps among them."""
    nodes, arrays, stack = [], [], [env]
    while stack:
        obj = stack.pop()
        items = obj.items() if isinstance(obj, dict) else enumerate(obj)
        for k, v in items:
            nodes.append((obj, k))
            if isinstance(v, (dict, list)):
                stack.append(v)
                if isinstance(v, dict) and set(v) == {"nd", "shape", "data"}:
                    arrays.append(v)
    return nodes, arrays


def _perturb(rng: random.Random, v):
    if isinstance(v, bool):
        return not v
    if isinstance(v, int):
        big = v * 2**32 if abs(v) < 2**64 else 1
        return rng.choice([v + 1, v - 1, -v, -v - 1, big, 2**64 - 1 - v if 0 <= v < 2**64 else 0])
    if isinstance(v, float):
        return rng.choice([-v, v * 1e300, math.nan, int(v) if math.isfinite(v) else 0])
    if isinstance(v, str):
        return rng.choice([v + "x", (v * 300)[:70_000], "", v.upper(), v.encode()])
    if isinstance(v, bytes):
        return rng.choice([v[:-1], v + b"\x00", (v * 2)[:70_000], v.decode("latin-1"), bytes(len(v))])
    if isinstance(v, list):
        return rng.choice([v + [0], v[:-1], (v * 2)[:70_000], [v], v[::-1]])
    if isinstance(v, dict):
        return rng.choice([{}, {**v, "zz": 0}, dict(list(v.items())[:-1]), [v]])
    return None


def _reshape(rng: random.Random, a: dict) -> None:
    """Re-shape / re-type one array map, often consistently (the data length matching)."""
    r = rng.random()
    if r < 0.3 and isinstance(a["shape"], list) and a["shape"]:
        shape = list(a["shape"])
        shape[rng.randrange(len(shape))] = rng.choice([0, 1, 2, 5, 2**31 - 1, 2**31, 2**64 - 1])
    else:
        dims = [0, 0, 1, 1, 2, 3, 4, 9, rng.randrange(50), 2**31 - 1, 2**31, 2**40, 2**64 - 1]
        shape = [rng.choice(dims) for _ in range(rng.randrange(8))]
    a["shape"] = shape
    if rng.random() < 0.3:
        a["nd"] = rng.choice(["f4", "f8", "i4", "i8", "u1", "b1", "f2", "O", "<f8", ""])
    dt = wire.ALLOWED_DTYPES.get(a["nd"]) if isinstance(a["nd"], str) else None
    ints = all(type(d) is int for d in shape)  # an earlier mutation may have put anything there
    n = math.prod(shape) * (dt.itemsize if dt is not None else 8) if ints else -1
    if 0 <= n <= 4096 and rng.random() < 0.7:
        a["data"] = rng.choice([bytes(n), rng.randbytes(n), (b"\x00\x00\x00\x00\x00\x00\xf8\x7f" * n)[:n]])
    else:
        a["data"] = rng.randbytes(rng.randrange(64))


def mutate_structure(rng: random.Random, seed: bytes) -> bytes:
    env = msgpack.unpackb(seed, raw=False)
    raw = None
    for _ in range(rng.choice((1, 1, 1, 2, 3))):
        nodes, arrays = _nodes(env)
        op = rng.random()
        if op < 0.15 and arrays:
            _reshape(rng, rng.choice(arrays))
            continue
        parent, key = rng.choice(nodes)
        if op < 0.5:
            parent[key] = _extreme(rng)
        elif op < 0.7:
            parent[key] = _perturb(rng, parent[key])
        elif op < 0.8 and raw is None:
            parent[key], raw = _PH, rng.choice(RAW)
        elif isinstance(parent, dict):
            if op < 0.9:
                del parent[key]
            else:
                parent[rng.choice(["zz", b"v", "body", "nd", key + "_" if isinstance(key, str) else "k"])] = \
                    _extreme(rng)
        elif op < 0.9:
            parent.append(_extreme(rng))
        else:
            del parent[key]
    try:
        out = msgpack.packb(env, use_bin_type=True)
    except (ValueError, TypeError, OverflowError):  # not packable (e.g. nested past packb's limit)
        return seed[: rng.randrange(len(seed))]
    if raw is not None:
        out = out.replace(_PH_PACKED, raw, 1)
    return out


def mutate_bytes(rng: random.Random, seed: bytes, other: bytes) -> bytes:
    b = bytearray(seed)
    op = rng.random()
    if op < 0.3:
        for _ in range(rng.randint(1, 8)):
            b[rng.randrange(len(b))] ^= 1 << rng.randrange(8)
    elif op < 0.5:
        for _ in range(rng.randint(1, 4)):
            b[rng.randrange(len(b))] = rng.choice(SPECIAL_BYTES) if rng.random() < 0.7 else rng.randrange(256)
    elif op < 0.6:
        del b[rng.randrange(len(b)):]
    elif op < 0.7:
        b = b[: rng.randrange(len(b))] + other[rng.randrange(len(other)):]
    elif op < 0.85:
        i = rng.randrange(len(b))
        b[i: i + rng.randrange(6)] = rng.choice(RAW)
    elif op < 0.9:
        i = rng.randrange(len(b))
        del b[i: i + rng.randrange(1, 64)]
    elif op < 0.95:
        i, j = sorted(rng.randrange(len(b)) for _ in range(2))
        b[j:j] = b[i:j]
    else:
        b += rng.randbytes(rng.randrange(1, 16))
    return bytes(b)


def check_accepted(msg: wire.Message) -> None:
    """What an accepted message guarantees to the services."""
    assert msg.kind in wire.SCHEMAS and msg.run_id == RUN
    assert 0 <= msg.seq <= wire.INT64_MAX and math.isfinite(msg.t)
    assert len(msg.sender) <= wire.MAX_NAME_LEN
    for name, spec in wire.SCHEMAS[msg.kind].items():
        v = msg.body[name]
        if isinstance(spec, wire.Scalar) and v is not None and spec.type == "int":
            assert (spec.lo if spec.lo is not None else wire.INT64_MIN) <= v <= wire.INT64_MAX
        if isinstance(spec, wire.Scalar) and spec.choices:
            assert v in spec.choices
        if isinstance(spec, wire.Arr) and v is None:
            assert spec.optional
        elif isinstance(spec, wire.Arr):
            assert v.size <= wire.MAX_ARRAY_ELEMENTS


class Fuzz:
    def __init__(self):
        self.reasons: Counter = Counter()
        self.accepted = 0
        self.escapes: list[str] = []
        self.n = 0

    def run(self, payload: bytes) -> None:
        self.n += 1
        try:
            msg = wire.decode(payload, run_id=RUN)
        except wire.WireError as exc:
            assert exc.reason in wire.REASONS
            self.reasons[exc.reason] += 1
            return
        except Exception:  # noqa: BLE001 - the point of the test
            if len(self.escapes) < 5:
                self.escapes.append(f"{payload[:120].hex()}...({len(payload)} bytes)\n{traceback.format_exc()}")
            else:
                self.escapes.append("")
            return
        self.accepted += 1
        check_accepted(msg)


# --------------------------------------------------------------------------- the fuzz loop
def test_fuzz_decode_raises_only_wire_error_and_memory_stays_bounded():
    rng = random.Random(SEED)
    fuzz = Fuzz()
    rss0 = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024
    t0 = time.perf_counter()
    for i in range(N_CASES):
        seed = SEEDS[i % len(SEEDS)]
        if rng.random() < 0.55:
            payload = mutate_structure(rng, seed)
        else:
            payload = mutate_bytes(rng, seed, rng.choice(SEEDS))
        fuzz.run(payload)
    wall = time.perf_counter() - t0
    rss_growth = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024 - rss0
    print(f"\nwire fuzz: {fuzz.n} cases in {wall:.1f} s, {fuzz.accepted} accepted, "
          f"{len(fuzz.escapes)} escapes, max RSS growth {rss_growth / 2**20:.1f} MiB, "
          f"rejections {dict(fuzz.reasons.most_common())}")
    assert fuzz.n >= 100_000
    assert not fuzz.escapes, f"{len(fuzz.escapes)} non-WireError exceptions, first:\n" + "\n".join(fuzz.escapes[:3])
    assert rss_growth < PEAK_BOUND
    # the mutations reach deep: most reasons occur (not only "malformed")
    assert len(fuzz.reasons) >= 10, fuzz.reasons


# --------------------------------------------------------------------------- worst cases
def _worst_cases() -> dict[str, bytes]:
    env = msgpack.unpackb(wire.encode("params", {"version": 0, "incarnation": "x", "method": "m",
                                                  "params": {}, "settings": {}},
                                      run_id=RUN, sender="s", seq=0), raw=False)

    def with_params(params) -> bytes:
        e = dict(env, body=dict(env["body"], params=params))
        return msgpack.packb(e, use_bin_type=True)

    big = (wire.MAX_MESSAGE_BYTES - 4096) // 8
    n16 = 16 * 2**20
    nested_maps = b"\xdc\x01\x00" + (b"\xdc\xff\xff" + b"\x80" * 0xFFFF) * 256
    # each array/map counts 1 + its entries: 2 * (1 + 60000) + 120000 maps + 1 + 2 < MAX_ITEMS
    just_under = b"\xdc\x00\x02" + (b"\xdc\xea\x60" + b"\x80" * 60000) * 2
    many_arrays = {f"p{i}": {"nd": "f8", "shape": [0], "data": b""} for i in range(2**16 - 1)}
    return {
        "16MiB flat array of empty maps": b"\xdd" + n16.to_bytes(4, "big") + b"\x80" * n16,
        "16MiB nested arrays of empty maps": nested_maps,
        "120000 empty maps (just under MAX_ITEMS)": just_under,
        "64MiB + 1 byte": b"\xc0" * (wire.MAX_MESSAGE_BYTES + 1),
        "claimed 4 GiB bin": b"\xc6\xff\xff\xff\xff" + b"\x00" * 1024,
        "claimed 4 GiB str": b"\xdb\xff\xff\xff\xff" + b"\x00" * 1024,
        "claimed 2**32 array": b"\xdd\xff\xff\xff\xff" + b"\xc0" * 1024,
        "claimed 2**32 map": b"\xdf\xff\xff\xff\xff" + b"\xc0" * 1024,
        "1024 nested arrays (parser limit)": b"\x91" * 1024 + b"\xc0",
        "1025 nested arrays": b"\x91" * 1025 + b"\xc0",
        "1000 str of 64 KiB": b"\xdc\x03\xe8" + (b"\xda\xff\xff" + b"x" * 0xFFFF) * 1000,
        "60000 bin of 1 KiB": b"\xdc\xea\x60" + (b"\xc5\x04\x00" + b"\x00" * 1024) * 60000,
        "zero-size array [0, 2**64-1]": with_params({"p": {"nd": "f8", "shape": [0, 2**64 - 1], "data": b""}}),
        "65535 zero-size arrays": with_params(many_arrays),
        "valid 64 MiB f8 array": with_params({"p": wire._enc_array(np.zeros(big))}),
        "64 MiB f8 array, NaN last": with_params({"p": wire._enc_array(np.r_[np.zeros(big - 1), np.nan])}),
        "64 MiB array, shape lies": with_params({"p": {"nd": "f8", "shape": [2**26 + 1], "data": bytes(big * 8)}}),
    }


def test_worst_cases_are_fast_and_bounded_in_memory():
    peaks = {}
    for name, payload in _worst_cases().items():
        tracemalloc.start()
        t0 = time.perf_counter()
        try:
            try:
                wire.decode(payload, run_id=RUN)
                outcome = "accepted"
            except wire.WireError as exc:
                outcome = exc.reason
            elapsed = time.perf_counter() - t0
            peak = tracemalloc.get_traced_memory()[1]
        finally:
            tracemalloc.stop()
        del payload
        peaks[name] = (outcome, round(peak / 2**20, 1), round(elapsed, 3))
        assert peak < PEAK_BOUND, (name, peaks[name])
        assert elapsed < 5.0, (name, peaks[name])
    print("\nworst cases (outcome, tracemalloc peak MiB, s):")
    for name, row in peaks.items():
        print(f"  {name}: {row}")
    assert peaks["120000 empty maps (just under MAX_ITEMS)"][0] == "envelope"
    assert peaks["valid 64 MiB f8 array"][0] == "accepted"
    assert peaks["64 MiB f8 array, NaN last"][0] == "nonfinite"
    for name in ("16MiB flat array of empty maps", "16MiB nested arrays of empty maps", "64MiB + 1 byte",
                 "1024 nested arrays (parser limit)", "1025 nested arrays", "zero-size array [0, 2**64-1]",
                 "64 MiB array, shape lies"):
        assert peaks[name][0] == "limit", (name, peaks[name])


# --------------------------------------------------------------------------- hypothesis: structured
_scalars = (st.none() | st.booleans() | st.integers(-2**63, 2**64 - 1) | st.floats()
            | st.text(max_size=12) | st.binary(max_size=24))
_values = st.recursive(
    _scalars, lambda ch: st.lists(ch, max_size=5) | st.dictionaries(st.text(max_size=6), ch, max_size=5),
    max_leaves=20)
_dims = st.integers(0, 4) | st.sampled_from([2**31 - 1, 2**31, 2**63 - 1, 2**64 - 1]) | st.integers(-2, 2**64 - 1)
_array_maps = st.fixed_dictionaries({
    "nd": st.sampled_from(sorted(wire.ALLOWED_DTYPES) + ["f2", "O"]) | _values,
    "shape": st.lists(_dims, max_size=8) | _values,
    "data": st.binary(max_size=96) | _values,
})
_SEED_ENVS = [msgpack.unpackb(p, raw=False) for p in SEEDS]


@st.composite
def envelopes(draw):
    env = msgpack.unpackb(msgpack.packb(draw(st.sampled_from(_SEED_ENVS)), use_bin_type=True), raw=False)
    for key in draw(st.lists(st.sampled_from(sorted(env)), max_size=2)):
        env[key] = draw(_values)
    body = env.get("body")
    if isinstance(body, dict):
        names = sorted(body) + ["extra_field"]
        for name in draw(st.lists(st.sampled_from(names), max_size=3)):
            op = draw(st.sampled_from(["value", "array", "delete"]))
            if op == "delete":
                body.pop(name, None)
            else:
                body[name] = draw(_values if op == "value" else _array_maps)
    return msgpack.packb(env, use_bin_type=True)


def _only_wire_error(payload):
    try:
        msg = wire.decode(payload, run_id=RUN)
    except wire.WireError as exc:
        assert exc.reason in wire.REASONS
    else:
        check_accepted(msg)


@settings(max_examples=400, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(envelopes())
def test_hypothesis_envelopes_with_arbitrary_fields(payload):
    _only_wire_error(payload)


@settings(max_examples=200, deadline=None)
@given(_values)
def test_hypothesis_arbitrary_msgpack_values(value):
    _only_wire_error(msgpack.packb(value, use_bin_type=True))


@settings(max_examples=200, deadline=None)
@given(st.binary(max_size=256))
def test_hypothesis_arbitrary_bytes(payload):
    _only_wire_error(payload)


# --------------------------------------------------------------------------- Service.decode
def test_service_decode_counts_every_failure_and_never_raises(monkeypatch):
    from services.base import Service
    from services.config import TrainConfig

    svc = Service(TrainConfig(run_id=RUN), bus=None)
    rng = random.Random(SEED)
    accepted = 0
    for i in range(2000):
        payload = mutate_structure(rng, SEEDS[i % len(SEEDS)])
        accepted += svc.decode(payload, None) is not None
    assert accepted + sum(svc.rejected.values()) == 2000
    before = svc.rejected["malformed"]

    for exc in (KeyError("a decoder bug"), MemoryError(), RecursionError()):
        def broken(*_a, exc=exc, **_k):
            raise exc

        monkeypatch.setattr(wire, "decode", broken)
        assert svc.decode(SEEDS[0], None) is None
    assert svc.rejected["malformed"] == before + 3
    sample = svc.registry.get_sample_value(
        "sage_messages_rejected_total", {**svc.labels, "reason": "malformed"})
    assert sample == svc.rejected["malformed"]


@pytest.mark.parametrize("payload", SEEDS[:2])
def test_seeds_round_trip(payload):
    assert wire.decode(payload, run_id=RUN).run_id == RUN
