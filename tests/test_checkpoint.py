"""Atomic checkpoints and learner resume."""
import json
import sys
import threading
from pathlib import Path

import pytest
import torch

sys.path.insert(0, str(Path(__file__).parent))
from services_fakes import FakeMethod  # noqa: E402

from common import checkpoint as ck  # noqa: E402
from common import keys, wire  # noqa: E402
from common.transport import Bus  # noqa: E402
from services.actor.service import ActorService  # noqa: E402
from services.config import TrainConfig  # noqa: E402
from services.learner.service import LearnerService  # noqa: E402


def test_save_is_weights_only_loadable_and_keeps_newest(tmp_path):
    for v in range(5):
        ck.save_checkpoint(tmp_path, v, {"w": torch.full((2,), float(v)), "version": v, "cfg": "{}"}, keep=2)
    assert [p.name for p in ck.list_checkpoints(tmp_path)] == ["ckpt_00000003.pt", "ckpt_00000004.pt"]
    d = torch.load(ck.checkpoint_path(tmp_path, 4), weights_only=True)
    assert d["version"] == 4 and torch.equal(d["w"], torch.full((2,), 4.0))


def test_crash_during_write_leaves_previous_checkpoint_intact(tmp_path, monkeypatch):
    ck.save_checkpoint(tmp_path, 1, {"version": 1})
    real_save = torch.save

    def crashing_save(obj, f):
        real_save(obj, f)
        f.truncate(10)  # half-written file, then the process "dies"
        raise OSError("disk gone")

    monkeypatch.setattr(torch, "save", crashing_save)
    with pytest.raises(OSError):
        ck.save_checkpoint(tmp_path, 2, {"version": 2})
    monkeypatch.undo()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["ckpt_00000001.pt", "manifest.json"]  # no temp, no torn v2
    assert ck.load_latest(tmp_path)["version"] == 1


def test_load_latest_skips_a_corrupt_newest_file(tmp_path):
    ck.save_checkpoint(tmp_path, 1, {"version": 1})
    ck.checkpoint_path(tmp_path, 2).write_bytes(b"not a checkpoint")
    (tmp_path / ".ckpt_x.tmp").write_bytes(b"partial")
    assert ck.load_latest(tmp_path)["version"] == 1
    assert ck.load_latest(tmp_path / "missing") is None


def run_learner(cfg, bus, method):
    learner = LearnerService(cfg, bus, 0, method=method)
    # feed synthetic chunks from a fake actor thread until the budget is reached
    from services_fakes import FakeBatchEnv, fake_propose

    stop = threading.Event()
    actor = ActorService(cfg, bus, 0, stop=stop, env=FakeBatchEnv(2), propose=fake_propose)
    at = threading.Thread(target=actor.run, daemon=True)
    at.start()
    learner.run()
    stop.set()
    at.join(5)
    return learner, actor


def test_learner_resumes_from_checkpoint_and_version_keeps_increasing(tmp_path):
    cfg = TrainConfig(run_id="ck", run_dir=str(tmp_path / "run"), updates=3, chunk_len=4, actors=1,
                      envs_per_actor=2, checkpoint_every=1, method="happo").validate()
    bus = Bus.open(inprocess=True)
    try:
        first, _ = run_learner(cfg, bus, FakeMethod())
        assert first.version == 3 and first.updates == 3
        saved = ck.load_latest(Path(cfg.run_dir) / "checkpoints")
        assert saved["version"] == 3 and saved["method"]["n"] == 3
        TrainConfig.from_dict(__import__("json").loads(saved["config"]))  # config round-trips

        # restart with a larger budget: same run dir, fresh method object
        cfg.updates = 5
        restored = FakeMethod()
        seen = []
        bus.subscribe(keys.params(cfg.run_id), lambda k, p: seen.append(wire.decode(p, run_id="ck").body))
        second, actor = run_learner(cfg, bus, restored)
        assert second.resumed_from == 3
        assert restored.n == 5                                  # method state was restored, then 2 updates
        assert second.version == 6 and second.updates == 5     # 3 -> 4 (restored publish) -> 6
        versions = [b["version"] for b in seen if b["incarnation"] == second.incarnation]
        assert versions[0] == 4 and versions == sorted(versions)
        # the actor adopted the restored learner's parameters (new incarnation)
        assert actor.params["incarnation"] == second.incarnation
        lines = (Path(cfg.run_dir) / "metrics.jsonl").read_text().splitlines()
        assert len(lines) == 5
    finally:
        bus.close()


def test_learner_refuses_a_checkpoint_whose_trees_mean_something_else(tmp_path):
    """The same dense straight-through weights are another policy under another
    split_k: resuming a sparse run as dense (or the reverse) is refused, by name."""
    cfg = TrainConfig(run_id="ck", run_dir=str(tmp_path / "run"), updates=2, chunk_len=4, actors=1,
                      envs_per_actor=2, checkpoint_every=1, method="happo", algo={"split_k": 1}).validate()
    bus = Bus.open(inprocess=True)
    try:
        run_learner(cfg, bus, FakeMethod())
        dense = TrainConfig.from_dict(json.loads(cfg.to_json()))
        dense.override("algo", "split_k", 0)
        with pytest.raises(ValueError, match="algo.split_k = 1, this run has 0"):
            LearnerService(dense, bus, 0, method=FakeMethod()).try_resume()
        same = LearnerService(TrainConfig.from_dict(json.loads(cfg.to_json())), bus, 0, method=FakeMethod())
        assert same.try_resume() and same.resumed_from == 2
    finally:
        bus.close()


# ---------------------------------------------------------------- issue 32, defect 5
def test_junk_files_named_like_checkpoints_never_push_the_real_ones_out(tmp_path):
    for v in (99999997, 99999998, 99999999):
        (tmp_path / f"ckpt_{v}.pt").write_bytes(b"junk")
    for v in range(1, 6):
        ck.save_checkpoint(tmp_path, v, {"version": v}, keep=2)
    names = sorted(p.name for p in tmp_path.iterdir())
    assert names == ["ckpt_00000004.pt", "ckpt_00000005.pt", "ckpt_99999997.pt", "ckpt_99999998.pt",
                     "ckpt_99999999.pt", "manifest.json"]          # junk neither counted nor deleted
    assert [p.name for p in ck.list_checkpoints(tmp_path)] == ["ckpt_00000004.pt", "ckpt_00000005.pt"]
    assert ck.load_latest(tmp_path)["version"] == 5


def test_a_damaged_newest_checkpoint_falls_back_with_a_warning(tmp_path, caplog):
    for v in (1, 2, 3):
        ck.save_checkpoint(tmp_path, v, {"version": v, "w": torch.zeros(64)})
    p = ck.checkpoint_path(tmp_path, 3)
    data = bytearray(p.read_bytes())
    data[-40] ^= 0xFF                                  # one flipped byte: torch may still load it
    p.write_bytes(bytes(data))
    with caplog.at_level("WARNING", logger="common.checkpoint"):
        assert ck.load_latest(tmp_path)["version"] == 2
    assert "ckpt_00000003.pt does not load" in caplog.text and "hash" in caplog.text
    # a valid checkpoint of another version under this name is no better
    torch.save({"version": 7}, ck.checkpoint_path(tmp_path, 2))
    assert ck.load_latest(tmp_path)["version"] == 1


def test_a_directory_whose_checkpoints_all_fail_refuses_to_start_over(tmp_path):
    for v in (1, 2):
        ck.save_checkpoint(tmp_path, v, {"version": v})
    for p in ck.list_checkpoints(tmp_path):
        p.write_bytes(b"\x00" * 100)
    with pytest.raises(ck.CheckpointError, match="none of its 2 checkpoint"):
        ck.load_latest(tmp_path)
    (tmp_path / ck.MANIFEST).unlink()                  # without the manifest: the files themselves
    with pytest.raises(ck.CheckpointError):
        ck.load_latest(tmp_path)
    assert ck.load_latest(tmp_path / "empty") is None  # nothing there: a fresh start is right


def test_learner_with_every_checkpoint_corrupt_stops_with_one_line_and_exit_4(tmp_path, caplog):
    import signal

    from common.status import EXIT_FATAL
    from services.base import run_entry

    cfg = TrainConfig(run_id="ck", run_dir=str(tmp_path / "run"), updates=2, chunk_len=4, actors=1,
                      envs_per_actor=2, checkpoint_every=1, method="happo").validate()
    bus = Bus.open(inprocess=True)
    try:
        run_learner(cfg, bus, FakeMethod())
    finally:
        bus.close()
    ckdir = Path(cfg.run_dir) / "checkpoints"
    assert ck.list_checkpoints(ckdir)
    for p in ck.list_checkpoints(ckdir):
        p.write_bytes(b"corrupt")
    with pytest.raises(ck.CheckpointError):            # never a silent restart from update 0
        LearnerService(cfg, None, 0, method=FakeMethod()).try_resume()
    path = tmp_path / "cfg.json"
    path.write_text(cfg.to_json())
    handlers = {s: signal.getsignal(s) for s in (signal.SIGTERM, signal.SIGINT)}
    try:
        with caplog.at_level("ERROR"):
            code = run_entry("learner", lambda c, b, m, r, s: LearnerService(c, b, m, r, s, method=FakeMethod()),
                             ["--config", str(path)])
    finally:
        for sig, h in handlers.items():
            signal.signal(sig, h)
    errors = [r for r in caplog.records if r.levelname == "ERROR"]
    assert code == EXIT_FATAL == 4
    assert len(errors) == 1 and "refusing to start over" in errors[0].getMessage()
    assert "\n" not in errors[0].getMessage()
