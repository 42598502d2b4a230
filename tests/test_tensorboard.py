"""The learner's TensorBoard event files (<run_dir>/tb/) hold the metrics rows:
read back here by parsing the TFRecord framing with tensorboardX's own protos."""
import json
import math
import struct

import pytest

pytest.importorskip("tensorboardX")

from sage.cli import main  # noqa: E402
from services.learner.service import MetricsLog  # noqa: E402


def read_scalars(logdir) -> dict[str, dict[int, float]]:
    """tag -> step -> value over every event file of ``logdir``, in file-name
    order, applying TensorBoard's purge: a session START at step s drops the
    earlier events at steps >= s."""
    from tensorboardX.proto.event_pb2 import Event, SessionLog

    out: dict[str, dict[int, float]] = {}
    files = sorted(logdir.glob("events.out.tfevents.*"))
    assert files, f"no event files in {logdir}"
    for path in files:
        data = path.read_bytes()
        pos = 0
        while pos < len(data):
            (length,) = struct.unpack("<Q", data[pos:pos + 8])
            record = data[pos + 12:pos + 12 + length]        # after the length and its crc
            assert len(record) == length, f"{path}: torn record"
            pos += 12 + length + 4                           # and the data's crc
            ev = Event.FromString(record)
            if ev.HasField("session_log") and ev.session_log.status == SessionLog.START:
                for series in out.values():
                    for step in [s for s in series if s >= ev.step]:
                        del series[step]
            for v in ev.summary.value:
                out.setdefault(v.tag, {})[ev.step] = v.simple_value
    return out


def assert_events_match(rows, scalars):
    numeric = {k for r in rows for k, v in r.items() if isinstance(v, (int, float)) and not isinstance(v, bool)}
    assert set(scalars) == numeric
    for r in rows:
        for k, v in r.items():
            if k in numeric and v is not None:
                got = scalars[k][r["update"]]
                # simple_value is a float32
                assert (math.isnan(got) and math.isnan(v)) or got == pytest.approx(v, rel=1e-6, abs=1e-30), (k, v, got)
    assert all(set(s) <= {r["update"] for r in rows} for s in scalars.values())


def test_two_update_run_writes_the_metrics_as_tensorboard_scalars(tmp_path):
    run = tmp_path / "tb_run"
    assert main(["train", "--method", "happo_cbf", "--updates", "2", "--envs-per-actor", "2", "--chunk-len", "8",
                 "--eval-episodes", "0", "--run-dir", str(run), "--quiet"]) == 0
    rows = [json.loads(x) for x in (run / "metrics.jsonl").read_text().splitlines()]
    assert [r["update"] for r in rows] == [1, 2]
    scalars = read_scalars(run / "tb")
    assert {"reward_mean", "env_steps", "update_s"} <= set(scalars)
    assert_events_match(rows, scalars)


def test_resumed_log_continues_the_event_directory_and_purges_rolled_back_updates(tmp_path):
    log = MetricsLog(tmp_path, upto=0, tensorboard=True, events_suffix="first")
    for u in (1, 2, 3):
        log.append({"update": u, "loss": float(u), "note": "x", "sr": None})
    log.close()
    # a restart from the checkpoint after update 2: update 3 is redone with another value
    log = MetricsLog(tmp_path, upto=2, tensorboard=True, events_suffix="second")
    log.append({"update": 3, "loss": 30.0, "note": "x", "sr": 0.5})
    log.close()
    assert len(list((tmp_path / "tb").glob("events.out.tfevents.*"))) == 2
    rows = [json.loads(x) for x in (tmp_path / "metrics.jsonl").read_text().splitlines()]
    scalars = read_scalars(tmp_path / "tb")
    assert scalars["loss"] == {1: 1.0, 2: 2.0, 3: 30.0} and scalars["sr"] == {3: 0.5}
    assert_events_match(rows, scalars)


def test_tensorboard_off_writes_no_events(tmp_path):
    log = MetricsLog(tmp_path, upto=0, tensorboard=False)
    log.append({"update": 1, "loss": 1.0})
    log.close()
    assert log.events is None and not (tmp_path / "tb").exists()
