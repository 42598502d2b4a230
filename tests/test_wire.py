"""Wire format: round trips and every rejection reason (docs/wire.md)."""
import msgpack
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from common import keys, wire

RUN = "run-a"


def shield_req(B=3, M=4):
    rng = np.random.default_rng(0)
    return {"a_prop": rng.uniform(-1, 1, (B, 9)), "C": rng.normal(size=(B, M, 9)), "c": rng.normal(size=(B, M)),
            "row_mask": rng.random((B, M)) < 0.5, "fixed_mask": np.zeros((B, 9), bool)}


def enc(body, kind="shield_req", run=RUN):
    return wire.encode(kind, body, run_id=run, sender="actor/0", seq=7)


def reason_of(payload, **kw):
    with pytest.raises(wire.WireError) as e:
        wire.decode(payload, run_id=kw.pop("run_id", RUN), **kw)
    return e.value.reason


def test_round_trip_keeps_dtype_shape_values_and_header():
    body = shield_req()
    msg = wire.decode(enc(body), run_id=RUN, expect="shield_req")
    assert (msg.kind, msg.run_id, msg.sender, msg.seq) == ("shield_req", RUN, "actor/0", 7)
    for k, v in body.items():
        assert msg.body[k].dtype == v.dtype and msg.body[k].shape == v.shape
        np.testing.assert_array_equal(msg.body[k], v)


@settings(max_examples=30, deadline=None)
@given(st.sampled_from(["f4", "f8", "i4", "i8", "u1", "b1"]),
       st.lists(st.integers(0, 4), min_size=0, max_size=4), st.integers(0, 2**31 - 1))
def test_params_arrays_round_trip_any_allowed_dtype(dt, shape, seed):
    a = np.asarray(np.random.default_rng(seed).normal(size=shape) * 10).astype(wire.ALLOWED_DTYPES[dt])
    body = {"version": 3, "incarnation": "x", "method": "sage", "params": {"p": a}, "settings": {"kappa": 2.0}}
    out = wire.decode(enc(body, "params"), run_id=RUN).body["params"]["p"]
    assert out.dtype == a.dtype and out.shape == a.shape
    np.testing.assert_array_equal(out, a)


def test_big_endian_input_is_sent_little_endian():
    a = np.arange(6, dtype=">f8").reshape(2, 3)
    body = {"version": 0, "incarnation": "x", "method": "m", "params": {"p": a}, "settings": {}}
    out = wire.decode(enc(body, "params"), run_id=RUN).body["params"]["p"]
    np.testing.assert_array_equal(out, a)


def test_encoder_refuses_dtype_outside_allow_list():
    body = shield_req()
    body["a_prop"] = body["a_prop"].astype(np.float16)
    with pytest.raises(TypeError):
        enc(body)


def test_truncated_and_garbage_bytes_are_malformed():
    p = enc(shield_req())
    for cut in (1, len(p) // 2, len(p) - 1):
        assert reason_of(p[:cut]) == "malformed"
    assert reason_of(b"\xc1\xc1") == "malformed"
    assert reason_of(p + b"\x00") == "malformed"  # trailing bytes


def test_version_run_and_kind_checks():
    env = msgpack.unpackb(enc(shield_req()), raw=False)
    env["v"] = wire.SCHEMA_VERSION + 1
    assert reason_of(msgpack.packb(env)) == "version"
    assert reason_of(enc(shield_req(), run="run-b")) == "run_id"
    assert reason_of(enc(shield_req()), expect="traj") == "kind"
    env = msgpack.unpackb(enc(shield_req()), raw=False)
    env["kind"] = "pickle"
    assert reason_of(msgpack.packb(env)) == "kind"
    del env["sender"]
    assert reason_of(msgpack.packb(env)) == "envelope"
    assert reason_of(msgpack.packb([1, 2])) == "envelope"


def _tamper(field, **changes):
    env = msgpack.unpackb(enc(shield_req()), raw=False)
    env["body"][field].update(changes)
    return msgpack.packb(env, use_bin_type=True)


def test_wrong_dtype_rejected():
    assert reason_of(_tamper("a_prop", nd="f2")) == "dtype"
    # a float array where a bool mask is expected: allowed dtype, wrong category
    b = shield_req()
    b["row_mask"] = b["row_mask"].astype(np.float64)
    assert reason_of(enc(b)) == "dtype"
    # bool bytes must be 0/1
    env = msgpack.unpackb(enc(shield_req()), raw=False)
    env["body"]["row_mask"]["data"] = bytes([2]) * len(env["body"]["row_mask"]["data"])
    assert reason_of(msgpack.packb(env, use_bin_type=True)) == "dtype"


def test_nan_and_inf_rejected():
    for bad in (np.nan, np.inf, -np.inf):
        b = shield_req()
        b["c"][1, 2] = bad
        assert reason_of(enc(b)) == "nonfinite"
    b = {"version": 0, "incarnation": "x", "method": "m", "params": {"p": np.array([np.nan])}, "settings": {}}
    assert reason_of(enc(b, "params")) == "nonfinite"
    b = {"version": 0, "incarnation": "x", "method": "m", "params": {}, "settings": {"kappa": float("nan")}}
    assert reason_of(enc(b, "params")) == "nonfinite"


def test_wrong_shapes_rejected():
    b = shield_req()
    b["a_prop"] = b["a_prop"][:, :8]           # fixed size 9
    assert reason_of(enc(b)) == "shape"
    b = shield_req()
    b["c"] = b["c"][:2]                          # B disagrees across fields
    assert reason_of(enc(b)) == "shape"
    b = shield_req()
    b["C"] = b["C"][:, :3]                       # M disagrees between C and c
    assert reason_of(enc(b)) == "shape"
    b = shield_req()
    b["a_prop"] = b["a_prop"][None]              # rank
    assert reason_of(enc(b)) == "shape"
    assert reason_of(_tamper("a_prop", shape=[3, 10])) == "shape"   # bytes vs shape


def test_missing_unknown_and_mistyped_fields():
    b = shield_req()
    del b["fixed_mask"]
    assert reason_of(enc(b)) == "missing_field"
    b = shield_req()
    b["extra"] = 1
    assert reason_of(enc(b)) == "unknown_field"
    body = {"version": "3", "incarnation": "x", "method": "m", "params": {}, "settings": {}}
    assert reason_of(enc(body, "params")) == "type"
    b = shield_req()
    b["a_prop"] = [[0.0] * 9] * 3               # a list is not an array map
    assert reason_of(enc(b)) == "type"


def test_traj_batch_concatenates_env_axis():
    def chunk(K, seed):
        r = np.random.default_rng(seed)
        T = 3
        return {"obs": r.normal(size=(T, K, 3, 2)), "state": r.normal(size=(T, K, 4)),
                "C": r.normal(size=(T, K, 2, 9)), "c": r.normal(size=(T, K, 2)),
                "row_mask": np.ones((T, K, 2), bool), "fixed_mask": np.zeros((T, K, 9), bool),
                **{k: r.normal(size=(T, K, 9)) for k in ("a_st", "a_bar", "a_prop", "a_exec")},
                "logp": r.normal(size=(T, K, 3)), "leaf": np.zeros((T, K, 3), np.int64),
                "shield_status": np.zeros((T, K), np.int32),
                "reward": r.normal(size=(T, K)), "terminated": np.zeros((T, K), bool),
                "truncated": np.zeros((T, K), bool), "final_state": np.zeros((T, K, 4)), 
                "final_obs": np.zeros((T, K, 3, 2), np.float32),
                "last_state": r.normal(size=(K, 4)), "last_obs": r.normal(size=(K, 3, 2))}
    a, b = chunk(2, 0), chunk(3, 1)
    out = wire.traj_batch([a, b])
    assert out["obs"].shape == (3, 5, 3, 2) and out["last_state"].shape == (5, 4)
    np.testing.assert_array_equal(out["reward"][:, 2:], b["reward"])
    np.testing.assert_array_equal(out["last_obs"][:2], a["last_obs"])
    b["state"] = b["state"][:, :, :3]
    with pytest.raises(ValueError):
        wire.traj_batch([a, b])


def test_keys_are_scoped_and_ids_cannot_inject_wildcards():
    assert keys.traj("r1", 3) == "sage/r1/traj/3"
    assert keys.status("r1", "actor", 2) == "sage/r1/status/actor/2"
    assert keys.shield("r1") == "sage/r1/shield/0" and keys.shield("r1", 2) == "sage/r1/shield/2" and keys.params("r1") == "sage/r1/params"
    assert keys.control("r1") == "sage/r1/control"
    for bad in ("a/b", "*", "a$", "", "x y", "**"):
        with pytest.raises(ValueError):
            keys.traj(bad, 0)
    with pytest.raises(ValueError):
        keys.status("r1", "hacker", 0)


# --------------------------------------------------------------------------- hardening regressions
def _params_env():
    body = {"version": 0, "incarnation": "x", "method": "m", "params": {"p": np.ones(2)}, "settings": {}}
    return msgpack.unpackb(enc(body, "params"), raw=False)


def _status_body(**changes):
    body = {"role": "actor", "id": "0", "state": "running", "pid": 1, "uptime_s": 1.0, "version": -1,
            "env_steps": 0, "env_steps_per_s": 0.0, "updates": 0, "success_rate": None,
            "shield_p99_s": None, "message": "", "extra": {}}
    body.update(changes)
    return body


@pytest.mark.parametrize("shape", [[0, 2**64 - 1], [2**64 - 1, 0], [0, 2**31, 2**31, 2**31], [0, 2**40],
                                   [2**13, 2**13, 2**1]])
def test_zero_size_array_with_huge_dims_is_a_limit_rejection(shape):
    # used to escape decode as numpy's "array is too big" ValueError
    env = _params_env()
    env["body"]["params"]["p"] = {"nd": "f8", "shape": shape, "data": b""}
    assert reason_of(msgpack.packb(env, use_bin_type=True)) == "limit"


def test_zero_size_arrays_within_limits_still_decode():
    env = _params_env()
    env["body"]["params"]["p"] = {"nd": "f8", "shape": [0, 2**20], "data": b""}
    out = wire.decode(msgpack.packb(env, use_bin_type=True), run_id=RUN).body["params"]["p"]
    assert out.shape == (0, 2**20)
    b = shield_req(M=0)                                   # no safety rows: C is [B, 0, 9]
    assert wire.decode(enc(b), run_id=RUN).body["C"].shape == (3, 0, 9)


def test_oversized_empty_map_message_is_rejected_fast_without_allocating():
    import time
    import tracemalloc
    n = 16 * 2**20  # 16 MiB: one array of 16M empty maps (cost +1.2 GB RSS and 4.3 s before)
    flat = b"\xdd" + n.to_bytes(4, "big") + b"\x80" * n
    nested = (b"\xdc\xff\xff" + b"\x80" * 0xFFFF) * 256                  # 256 arrays of 65535 maps
    nested = b"\xdc" + (256).to_bytes(2, "big") + nested
    for payload in (flat, nested):
        tracemalloc.start()
        t0 = time.perf_counter()
        try:
            assert reason_of(payload) == "limit"
            elapsed = time.perf_counter() - t0
            peak = tracemalloc.get_traced_memory()[1]
        finally:
            tracemalloc.stop()
        assert elapsed < 1.0 and peak < 64 * 2**20, (elapsed, peak)
    assert reason_of(b"\x00" * (wire.MAX_MESSAGE_BYTES + 1)) == "limit"


def test_claimed_giant_lengths_and_deep_nesting_are_rejected():
    for head in (b"\xdb\xff\xff\xff\xff", b"\xc6\xff\xff\xff\xff", b"\xdd\xff\xff\xff\xff",
                 b"\xdf\xff\xff\xff\xff", b"\xc9\xff\xff\xff\xff\x01"):
        assert reason_of(head + b"\x00" * 64) in ("limit", "malformed")
    assert reason_of(msgpack.packb("x" * (wire.MAX_STR_BYTES + 1))) == "limit"
    assert reason_of(b"\x91" * 2000 + b"\xc0") == "limit"              # parser stack
    env = _params_env()
    deep = 0
    for _ in range(wire.MAX_DEPTH):
        deep = [deep]
    env["body"]["settings"]["kappa"] = deep
    assert reason_of(msgpack.packb(env, use_bin_type=True)) == "limit"


@pytest.mark.parametrize("field,value", [("version", -1), ("version", -2**63), ("version", 2**64 - 1)])
def test_negative_or_out_of_range_versions_rejected(field, value):
    body = {"version": value, "incarnation": "x", "method": "m", "params": {}, "settings": {}}
    assert reason_of(enc(body, "params")) == "value"


def test_status_version_may_be_minus_one_but_not_less():
    msg = wire.decode(enc(_status_body(version=-1), "status"), run_id=RUN)
    assert msg.body["version"] == -1
    assert reason_of(enc(_status_body(version=-2), "status")) == "value"
    for field in ("env_steps", "updates", "pid"):
        assert reason_of(enc(_status_body(**{field: -1}), "status")) == "value"


@pytest.mark.parametrize("seq", [-1, -2**63, 2**64 - 1])
def test_negative_or_huge_seq_rejected(seq):
    env = msgpack.unpackb(enc(shield_req()), raw=False)
    env["seq"] = seq
    assert reason_of(msgpack.packb(env, use_bin_type=True)) == "value"


@pytest.mark.parametrize("t", [float("nan"), float("inf"), -float("inf")])
def test_non_finite_time_rejected(t):
    env = msgpack.unpackb(enc(shield_req()), raw=False)
    env["t"] = t
    assert reason_of(msgpack.packb(env, use_bin_type=True)) == "nonfinite"


def test_unknown_status_state_and_control_command_rejected():
    for state in wire.STATUS_STATES:
        assert wire.decode(enc(_status_body(state=state), "status"), run_id=RUN).body["state"] == state
    assert reason_of(enc(_status_body(state="exploded"), "status")) == "value"
    assert reason_of(enc({"command": "rm -rf", "target": "*"}, "control")) == "value"


def test_long_strings_rejected():
    assert reason_of(wire.encode("control", {"command": "stop", "target": "*"}, run_id=RUN,
                                 sender="a" * (wire.MAX_NAME_LEN + 1), seq=0)) == "limit"
    assert reason_of(enc(_status_body(id="x" * (wire.MAX_NAME_LEN + 1)), "status")) == "limit"
    assert wire.decode(enc(_status_body(message="m" * wire.MAX_TEXT_LEN), "status"), run_id=RUN)
    assert reason_of(enc(_status_body(message="m" * (wire.MAX_TEXT_LEN + 1)), "status")) == "limit"
    assert reason_of(enc(_status_body(extra={"k" * (wire.MAX_NAME_LEN + 1): 1.0}), "status")) == "limit"


def test_version_must_be_the_int_one():
    for v in (1.0, True, "1", [1]):
        env = msgpack.unpackb(enc(shield_req()), raw=False)
        env["v"] = v
        assert reason_of(msgpack.packb(env, use_bin_type=True)) == "version"


def test_error_details_stay_short_for_huge_or_nested_values():
    nested = 0
    for _ in range(4):                                  # within MAX_DEPTH, 3**4 leaves
        nested = [nested] * 3
    for bad in (nested, "f" * 60000, b"\x00" * 60000, list(range(1000))):
        env = msgpack.unpackb(enc(shield_req()), raw=False)
        env["body"]["a_prop"]["nd"] = bad
        with pytest.raises(wire.WireError) as e:
            wire.decode(msgpack.packb(env, use_bin_type=True), run_id=RUN)
        assert e.value.reason == "dtype" and len(str(e.value)) < 200, str(e.value)
    env = msgpack.unpackb(enc(shield_req()), raw=False)
    env[b"k"] = 1                                                       # str and bytes keys mixed
    assert reason_of(msgpack.packb(env, use_bin_type=True)) == "envelope"
