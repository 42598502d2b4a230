"""Experiment tracking (services/learner/tracking.py): metric sections, the
metrics-file tail that feeds Weights & Biases, and `sage train --track` in W&B's
offline mode (WANDB_MODE=offline: no network), read back from the run's
``.wandb`` file (LevelDB log framing of wandb's own ``Record`` protos)."""
from __future__ import annotations

import json
import os
import struct
import sys

import pytest

from sage.cli import main
from services.learner.tracking import MetricsTail, flat_config, scalars_of, section


def test_metrics_are_grouped_by_section():
    expect = {"reward_mean": "train", "policy_loss": "train", "ep_success_mean": "train", "col_per_1k": "train",
              "margin_col_per_1k": "train", "success_rate_recent": "train", "entropy": "train",
              "deploy_sr": "deploy", "deploy_col_per_1k": "deploy", "deploy_probe_s": "system",
              "w_gap_first": "mechanism", "cos_ind_team_mean": "mechanism", "talo_condition_met": "mechanism",
              "proposal_violation_rate": "mechanism", "correction_st": "mechanism", "kappa": "mechanism",
              "sail_residual": "mechanism", "unfiltered_steps": "mechanism",
              "update": "system", "update_s": "system", "update_cpu_s": "system", "env_steps": "system",
              "chunks_stale": "system", "lag_max": "system", "time_s": "system", "version": "system"}
    assert {k: section(k) for k in expect} == expect
    row = {"update": 3, "env_steps": 48, "reward_mean": 0.5, "deploy_sr": None, "note": "x", "flag": True}
    assert scalars_of(row) == {"system/update": 3.0, "system/env_steps": 48.0, "train/reward_mean": 0.5}
    assert flat_config({"a": 1, "b": {"c": [1, 2], "d": None, "e": "s"}}) == {"a": 1, "b/c": "[1, 2]",
                                                                             "b/d": "null", "b/e": "s"}


def test_metrics_tail_hands_on_complete_rows_once_and_rereads_a_replaced_file(tmp_path):
    path = tmp_path / "metrics.jsonl"
    got = []
    tail = MetricsTail(path, got.append, poll_s=3600)   # polled by hand here
    tail.poll()                                          # no file yet: nothing
    with open(path, "w") as f:
        f.write(json.dumps({"update": 1}) + "\n" + json.dumps({"update": 2}) + "\n" + '{"upda')   # torn last line
    tail.poll()
    assert got == [{"update": 1}, {"update": 2}]
    with open(path, "a") as f:
        f.write('te": 3}\n')
    tail.poll()
    assert got[-1] == {"update": 3} and tail.rows == 3
    # a resumed learner rewrites the file atomically (rolled-back rows moved out): read from its start
    tmp = tmp_path / "new.jsonl"
    tmp.write_text(json.dumps({"update": 1}) + "\n" + json.dumps({"update": 2, "redo": True}) + "\n")
    os.replace(tmp, path)
    tail.poll()
    assert got[-2:] == [{"update": 1}, {"update": 2, "redo": True}]


def wandb_records(path) -> list:
    """wandb's ``Record`` protos of an offline run file (``run-<id>.wandb``): a 7-byte
    header, then LevelDB log records (32 KiB blocks, FULL/FIRST/MIDDLE/LAST chunks)."""
    from wandb.proto import wandb_internal_pb2 as pb

    data = path.read_bytes()
    assert data[:4] == b":W&B"
    pos, block, out, buf = 7, 32768, [], b""
    while pos + 7 <= len(data):
        if block - pos % block < 7:        # a block's tail too short for a header is padding
            pos += block - pos % block
            continue
        _crc, n, kind = struct.unpack("<IHB", data[pos:pos + 7])
        chunk, pos = data[pos + 7:pos + 7 + n], pos + 7 + n
        if kind == 1:
            out.append(chunk)
        elif kind == 2:
            buf = chunk
        elif kind == 3:
            buf += chunk
        elif kind == 4:
            out.append(buf + chunk)
    return [pb.Record.FromString(x) for x in out]


def finished_records(path, timeout_s: float = 30.0) -> list:
    """The run file's records once W&B's writer has written its last (``exit``) record:
    ``run.finish()`` hands the records to wandb's own writer process, which may still be
    writing when it returns."""
    import time

    deadline = time.monotonic() + timeout_s
    while True:
        records = wandb_records(path)
        if any(r.WhichOneof("record_type") == "exit" for r in records) or time.monotonic() > deadline:
            return records
        time.sleep(0.1)


def _items(update) -> dict:
    return {it.key or "/".join(it.nested_key): json.loads(it.value_json) for it in update}


def test_train_track_logs_metrics_config_and_final_eval_to_wandb_offline(tmp_path, monkeypatch, capsys):
    pytest.importorskip("wandb")
    monkeypatch.setenv("WANDB_MODE", "offline")   # no network, no account
    monkeypatch.setenv("WANDB_SILENT", "true")
    run = tmp_path / "r"
    assert main(["train", "--method", "happo_cbf", "--updates", "3", "--envs-per-actor", "2", "--chunk-len", "8",
                 "--eval-episodes", "1", "--metrics-port", "0", "--run-dir", str(run), "--quiet",
                 "--track", "--wandb-project", "sage-test"]) == 0
    capsys.readouterr()
    rows = [json.loads(x) for x in (run / "metrics.jsonl").read_text().splitlines() if x.strip()]
    summary = json.loads((run / "summary.json").read_text())
    (wb_file,) = (run / "wandb").glob("offline-run-*/run-*.wandb")
    assert summary["tracking"]["wandb"]["project"] == "sage-test"
    records = finished_records(wb_file)
    kinds = [r.WhichOneof("record_type") for r in records]
    # every metrics row once, by section, at its env steps
    history = [_items(r.history.item) for r in records if r.WhichOneof("record_type") == "history"]
    assert [h["system/update"] for h in history] == [r["update"] for r in rows] == [1, 2, 3]
    assert [h["system/env_steps"] for h in history] == [r["env_steps"] for r in rows]
    for h, r in zip(history, rows):
        assert h["train/reward_mean"] == pytest.approx(r["reward_mean"])
        assert h["mechanism/correction_mean"] == pytest.approx(r["correction_mean"])
    # the resolved config is the run's config
    (run_record,) = [r for r in records if r.WhichOneof("record_type") == "run"]
    config = {k: v["value"] if isinstance(v, dict) and "value" in v else v
              for k, v in _items(run_record.run.config.update).items()}
    saved = json.loads((run / "config.json").read_text())
    assert config["method"] == "happo_cbf" and config["run_id"] == saved["run_id"]
    assert config["algo"] == saved["algo"] and config["env"] == saved["env"]
    # the final evaluation is the W&B summary
    final = {}
    for r in records:
        if r.WhichOneof("record_type") == "summary":
            final.update(_items(r.summary.update))
    assert final["final/eval/success_rate"] == summary["eval"]["success_rate"]
    assert final["final/updates"] == 3 and "exit" in kinds


def test_track_without_wandb_is_one_line_and_exit_2(tmp_path, monkeypatch, capsys):
    monkeypatch.setitem(sys.modules, "wandb", None)   # `import wandb` raises ImportError
    run = tmp_path / "r"
    with pytest.raises(SystemExit) as exc:
        main(["train", "--updates", "1", "--run-dir", str(run), "--quiet", "--track"])
    assert exc.value.code == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "wandb" in err and "[wandb]" in err and "Traceback" not in err
    assert not run.exists()   # refused before anything was written
