"""Message sizes are bounded at the transport (issue 32, defect 8): Zenoh's own
``transport/link/rx/max_message_size`` on every session of a run (its bound:
the largest chunk it sends), so an oversized message is never reassembled,
and services refuse one past the run's bound before unpacking it."""
from __future__ import annotations

import socket
import sys
import threading
import time
from pathlib import Path

import numpy as np
from prometheus_client import CollectorRegistry

sys.path.insert(0, str(Path(__file__).parent))
from test_services import make_cfg  # noqa: E402

from common import wire  # noqa: E402
from common.transport import MAX_MESSAGE_SIZE_KEY, Bus, zenoh_config  # noqa: E402
from services.config import TrainConfig, TransportConfig  # noqa: E402
from services.shield.service import ShieldService  # noqa: E402


def _free_port() -> int:
    s = socket.socket()
    s.bind(("127.0.0.1", 0))
    port = s.getsockname()[1]
    s.close()
    return port


def test_the_runs_bound_covers_its_largest_chunk_and_goes_into_zenohs_config():
    from common.env.observations import OBS_DIM, STATE_DIM

    cfg = TrainConfig(run_id="x", chunk_len=64, envs_per_actor=64)
    T, K, M = cfg.chunk_len, cfg.envs_per_actor, cfg.env.max_rows
    body = {k: np.zeros(tuple({"T": T, "K": K, "M": M, "O": OBS_DIM, "S": STATE_DIM}.get(s, s) for s in spec.shape),
                        spec.send_dtype) for k, spec in wire.SCHEMAS["traj"].items() if isinstance(spec, wire.Arr)}
    body.update(actor_id=0, version=0, incarnation="i", env_steps=0, episodes=[{"success": 1.0}] * (T * K))
    assert len(wire.encode("traj", body, run_id="x", sender="actor/0", seq=0)) <= cfg.message_bytes_bound()
    assert TrainConfig(run_id="x").message_bytes_bound() == 8 * 2**20
    assert TrainConfig(run_id="x", transport=TransportConfig(max_message_bytes=2**40)).message_bytes_bound() \
        == wire.MAX_MESSAGE_BYTES
    zc = zenoh_config(max_message_bytes=3 * 2**20)
    assert zc.get_json(MAX_MESSAGE_SIZE_KEY) == str(3 * 2**20)


def test_a_link_never_delivers_a_message_past_its_limit():
    port = _free_port()
    limit = 1 << 20
    listener = Bus.open(listen=[f"tcp/127.0.0.1:{port}"], max_message_bytes=limit)
    sender = Bus.open(connect=[f"tcp/127.0.0.1:{port}"])
    got: list[int] = []
    try:
        listener.subscribe("limits/test", lambda _k, p: got.append(len(p)))
        deadline = time.monotonic() + 20
        while not got and time.monotonic() < deadline:   # until the link is up
            sender.publish("limits/test", b"x" * 1000)
            time.sleep(0.05)
        assert got
        sender.publish("limits/test", b"y" * (4 * limit))   # past the limit: dropped by the link
        # within it: still delivered after it. Sent until it arrives: delivery is best
        # effort, and on a loaded machine the link may drop the first copy while it
        # recovers from the oversized frame (seen in a full-suite run on 2 busy cores)
        deadline = time.monotonic() + 20
        while got[-1] != limit // 2 and time.monotonic() < deadline:
            sender.publish("limits/test", b"z" * (limit // 2))
            time.sleep(0.2)
        assert got[-1] == limit // 2 and 4 * limit not in got
    finally:
        sender.close()
        listener.close()


def test_services_refuse_a_payload_past_the_runs_bound_before_unpacking(tmp_path):
    cfg = make_cfg(tmp_path, transport=TransportConfig(max_message_bytes=1 << 20))
    shield = ShieldService(cfg, None, registry=CollectorRegistry(), stop=threading.Event())
    big = wire.encode("control", {"command": "stop", "target": "x" * 100}, run_id=cfg.run_id, sender="a", seq=0)
    assert shield.decode(big, "control") is not None
    assert shield.decode(big + b"\0" * (1 << 20), "control") is None
    assert shield.rejected["limit"] == 1


def test_the_new_bounds_refuse_values_that_would_disable_them():
    import pytest

    from services.config import ActorConfig, ShieldConfig

    for kw, name in ((dict(transport=TransportConfig(max_message_bytes=-1)), "max_message_bytes"),
                     (dict(max_seq_gap=0), "max_seq_gap"),
                     (dict(actor=ActorConfig(max_version_step=0)), "max_version_step"),
                     (dict(shield=ShieldConfig(max_pending_per_sender=0)), "max_pending_per_sender")):
        with pytest.raises(ValueError, match=name):
            TrainConfig(run_id="x", **kw).validate()
    TrainConfig(run_id="x", transport=TransportConfig(max_message_bytes=0)).validate()   # 0: the run's own bound
