"""The learner's TensorBoard event files (<run_dir>/tb/) hold the metrics rows
(tagged <section>/<key>, at the row's env steps) and the resolved config: read
back here by parsing the TFRecord framing with tensorboardX's own protos."""
import json
import math
import struct

import pytest

pytest.importorskip("tensorboardX")

from sage.cli import main  # noqa: E402
from services.learner.service import MetricsLog  # noqa: E402
from services.learner.tracking import SECTIONS, section  # noqa: E402


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
                if v.HasField("metadata") and v.metadata.plugin_data.plugin_name:   # text, hparams
                    continue
                out.setdefault(v.tag, {})[ev.step] = v.simple_value
    return out


def read_plugin_values(logdir) -> dict[str, bytes]:
    """tag -> serialized value of the plugin summaries (text, hparams)."""
    from tensorboardX.proto.event_pb2 import Event

    out = {}
    for path in sorted(logdir.glob("events.out.tfevents.*")):
        data, pos = path.read_bytes(), 0
        while pos < len(data):
            (length,) = struct.unpack("<Q", data[pos:pos + 8])
            ev = Event.FromString(data[pos + 12:pos + 12 + length])
            pos += 12 + length + 4
            for v in ev.summary.value:
                if v.HasField("metadata") and v.metadata.plugin_data.plugin_name:
                    out[v.tag] = v.SerializeToString()
    return out


def _x(row):
    return row.get("env_steps", row["update"])


def assert_events_match(rows, scalars):
    numeric = {k for r in rows for k, v in r.items() if isinstance(v, (int, float)) and not isinstance(v, bool)}
    assert set(scalars) == {f"{section(k)}/{k}" for k in numeric}
    assert all(tag.split("/")[0] in SECTIONS for tag in scalars)
    for r in rows:
        for k, v in r.items():
            if k in numeric and v is not None:
                got = scalars[f"{section(k)}/{k}"][_x(r)]
                # simple_value is a float32
                assert (math.isnan(got) and math.isnan(v)) or got == pytest.approx(v, rel=1e-6, abs=1e-30), (k, v, got)
    assert all(set(s) <= {_x(r) for r in rows} for s in scalars.values())


def test_two_update_run_writes_the_metrics_as_tensorboard_scalars(tmp_path):
    run = tmp_path / "tb_run"
    assert main(["train", "--method", "happo_cbf", "--updates", "2", "--envs-per-actor", "2", "--chunk-len", "8",
                 "--eval-episodes", "0", "--run-dir", str(run), "--quiet"]) == 0
    rows = [json.loads(x) for x in (run / "metrics.jsonl").read_text().splitlines()]
    assert [r["update"] for r in rows] == [1, 2]
    scalars = read_scalars(run / "tb")
    assert {"train/reward_mean", "system/env_steps", "system/update_s", "mechanism/correction_mean",
            "train/policy_loss"} <= set(scalars)
    # the x-axis is env steps: the steps of a series are the rows' env steps
    assert sorted(scalars["train/reward_mean"]) == [r["env_steps"] for r in rows] != [1, 2]
    assert_events_match(rows, scalars)
    # the resolved config, as text and as HParams
    plugins = read_plugin_values(run / "tb")
    config = json.loads((run / "config.json").read_text())
    assert "config/text_summary" in plugins and f'"run_id": "{config["run_id"]}"'.encode() in plugins["config/text_summary"]
    start = plugins["_hparams_/session_start_info"]
    assert b"algo/actor_lr" in start and b"happo_cbf" in start and b"method" in start


def test_resumed_log_continues_the_event_directory_and_purges_rolled_back_updates(tmp_path):
    log = MetricsLog(tmp_path, upto=0, tensorboard=True, events_suffix="first")
    for u in (1, 2, 3):
        log.append({"update": u, "env_steps": 100 * u, "loss": float(u), "note": "x", "sr": None})
    log.close()
    # a restart from the checkpoint after update 2: update 3 is redone with another value
    # (and another batch size: the purge works in env steps)
    log = MetricsLog(tmp_path, upto=2, tensorboard=True, events_suffix="second")
    log.append({"update": 3, "env_steps": 250, "loss": 30.0, "note": "x", "sr": 0.5})
    log.close()
    assert len(list((tmp_path / "tb").glob("events.out.tfevents.*"))) == 2
    rows = [json.loads(x) for x in (tmp_path / "metrics.jsonl").read_text().splitlines()]
    scalars = read_scalars(tmp_path / "tb")
    assert scalars["train/loss"] == {100: 1.0, 200: 2.0, 250: 30.0} and scalars["train/sr"] == {250: 0.5}
    assert scalars["system/update"] == {100: 1.0, 200: 2.0, 250: 3.0}
    assert_events_match(rows, scalars)


def test_tensorboard_off_writes_no_events(tmp_path):
    log = MetricsLog(tmp_path, upto=0, tensorboard=False)
    log.append({"update": 1, "loss": 1.0})
    log.close()
    assert log.events is None and not (tmp_path / "tb").exists()
