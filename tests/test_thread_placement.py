"""deploy/threads.py: the in-process run is the run driver's third placement.
Run with the small fakes of tests/services_fakes.py, it writes the same
records as the process placements (``supervisor.jsonl`` from
``supervisor_start`` to ``supervisor_exit``, ``status.json``), and ends the
same ways: the learner's budget (exit 0), a service that raises (exit 1, or 4
for a ``CheckpointError``, which restarting cannot fix), a signal (128 + signal)."""
import json
import os
import signal
import sys
import threading
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).parent))
from services_fakes import FakeBatchEnv, FakeMethod, fake_propose, fake_solve  # noqa: E402
from test_services import make_cfg  # noqa: E402

from common.checkpoint import CheckpointError  # noqa: E402
from deploy.threads import run_inprocess  # noqa: E402


def run(cfg, method, **kw):
    envs = [FakeBatchEnv(2, seed=i) for i in range(cfg.actors)]
    return run_inprocess(cfg, progress=False, method=method, envs=envs, propose=fake_propose, solve=fake_solve,
                         timeout_s=60, **kw)


def events(cfg) -> list[dict]:
    return [json.loads(line) for line in (Path(cfg.run_dir) / "supervisor.jsonl").read_text().splitlines()]


def test_a_thread_run_writes_the_drivers_records(tmp_path):
    cfg = make_cfg(tmp_path)
    out = run(cfg, FakeMethod())
    assert out["exit_code"] == 0 and out["updates"] == 3
    rows = events(cfg)
    assert rows[0]["event"] == "supervisor_start" and rows[-1] == {**rows[-1], "event": "supervisor_exit", "code": 0}
    assert sorted(r["service"] for r in rows if r["event"] == "start") == ["actor/0", "actor/1", "learner/0",
                                                                          "shield/0"]
    assert [r["code"] for r in rows if r["event"] == "exit" and r["service"] == "learner/0"] == [0]
    assert rows[-1]["message"] == "learner/0 finished"
    status = json.loads((Path(cfg.run_dir) / "status.json").read_text())
    assert status["placer"] == "threads" and status["services"]["learner/0"]["state"] == "done"
    assert status["status"]["members"]["learner/0"]["role"] == "learner"


class Raising(FakeMethod):
    def __init__(self, exc):
        super().__init__()
        self.exc = exc

    def update(self, batch, progress):
        raise self.exc


def test_a_service_that_raises_ends_the_run_with_exit_1_and_its_error(tmp_path):
    cfg = make_cfg(tmp_path)
    with pytest.raises(RuntimeError, match=r"service learner/0 failed: ValueError\('a bug'\)"):
        run(cfg, Raising(ValueError("a bug")))
    last = events(cfg)[-1]
    assert last["event"] == "supervisor_exit" and last["code"] == 1 and "a bug" in last["message"]


def test_a_checkpoint_error_is_one_line_and_exit_4(tmp_path):
    cfg = make_cfg(tmp_path)
    with pytest.raises(SystemExit, match="learner/0: no checkpoint loads"):
        run(cfg, Raising(CheckpointError("no checkpoint loads", ["ckpt_00000003.pt: hash mismatch"])))
    assert events(cfg)[-1]["code"] == 4


class Slow(FakeMethod):
    def __init__(self, started: threading.Event):
        super().__init__()
        self.started = started

    def update(self, batch, progress):
        self.started.set()
        return super().update(batch, progress)


@pytest.mark.skipif(threading.current_thread() is not threading.main_thread(), reason="signals need the main thread")
def test_sigint_stops_the_run_with_exit_130_as_a_process_placement_would(tmp_path):
    cfg = make_cfg(tmp_path, updates=10 ** 6)
    started = threading.Event()
    killer = threading.Thread(target=lambda: started.wait(60) and os.kill(os.getpid(), signal.SIGINT), daemon=True)
    killer.start()
    out = run(cfg, Slow(started))
    assert out["exit_code"] == 128 + signal.SIGINT and 1 <= out["updates"] < 10 ** 6
    last = events(cfg)[-1]
    assert last["code"] == 130 and last["message"] == "stopped by SIGINT"
