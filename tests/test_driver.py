"""deploy/driver.py: the one run driver under every process placement. A
placement here is a dozen lines of members held in memory (no processes), so
the driver's own rules are checked alone: the run ends when the member marked
``ends_run`` exits 0 (``on_finish`` first), when every wave-0 member is done,
when the placement gives up, or on a signal (exit code 128 + signal); the
records (``supervisor.jsonl``, ``status.json``, the final line) are written the
same whatever the placement; the shutdown goes wave by wave."""
from __future__ import annotations

import io
import json
import os
import signal
from dataclasses import dataclass

import pytest

from deploy.driver import EXIT_GAVE_UP, Member, RunDriver
from deploy.supervisor import ServiceSpec


@dataclass
class Knobs:
    poll_s: float = 0.0
    status_period_s: float = 0.0      # a status round every loop: status.json while running
    status_log_period_s: float = 10.0


class Scripted(RunDriver):
    """A placement whose members 'run' in memory: ``script[name]`` is the round in
    which that member exits and its exit code; a code of None never exits."""

    label = "scripted"

    def __init__(self, specs, run_dir, script, give_up_at=None):
        super().__init__([Member(s) for s in specs], run_dir, Knobs(), out=io.StringIO())
        self.script, self.round, self.give_up_at, self.stopped = script, 0, give_up_at, []

    def start(self):
        for m in self.members:
            m.state, m.starts = "running", 1
            self.event("start", service=m.spec.name, attempt=1)

    def poll_members(self):
        self.round += 1
        if self.round > 1000:   # a driver that never ends the run fails the test instead of hanging it
            self.finish(99, "runaway")
        if self.round == self.give_up_at:
            self.finish(EXIT_GAVE_UP, "giving up: scripted")
        for m in self.members:
            at, code = self.script.get(m.spec.name, (None, None))
            if m.state == "running" and at == self.round and code is not None:
                m.state, m.last_code = ("done" if code == 0 else "failed"), code
                self.event("exit", service=m.spec.name, code=code)
                if code == 0 and m.spec.ends_run:
                    self.finish(0, f"{m.spec.name} finished")

    def stop_wave(self, group):
        self.stopped.append(sorted(m.spec.name for m in group))
        for m in group:
            if m.state == "running":
                m.state = "stopped"


class Board:
    def __init__(self):
        self.stopped = self.closed = False

    def line(self):
        return "board"

    def snapshot(self):
        return {"learner/0": {"updates": 3}}

    def stop_run(self):
        self.stopped = True

    def close(self):
        self.closed = True


def specs():
    return [ServiceSpec("router", ["r"], stop_wave=1), ServiceSpec("learner", ["l"], ends_run=True),
            ServiceSpec("actor-0", ["a"])]


def rows(run_dir):
    return [json.loads(x) for x in (run_dir / "supervisor.jsonl").read_text().splitlines()]


def test_the_run_ending_member_ends_the_run_and_the_records_are_written(tmp_path):
    drv = Scripted(specs(), tmp_path, {"learner": (3, 0)})
    board = Board()
    code = drv.run(lambda: board, lambda status: status.stop_run(), install_signals=False)
    assert code == 0 and board.stopped and board.closed
    kinds = [r["event"] for r in rows(tmp_path)]
    assert kinds[0] == "supervisor_start" and kinds[-1] == "supervisor_exit"
    assert rows(tmp_path)[0]["services"] == ["router", "learner", "actor-0"]
    assert rows(tmp_path)[-1]["code"] == 0 and rows(tmp_path)[-1]["message"] == "learner finished"
    assert "shutdown" in kinds
    assert drv.stopped == [["actor-0", "learner"], ["router"]]   # wave 0 first, the router last
    status = json.loads((tmp_path / "status.json").read_text())
    assert status["placer"] == "scripted" and status["status"] == {"learner/0": {"updates": 3}}
    assert status["services"]["learner"] == {"state": "done", "pid": None, "starts": 1, "last_code": 0}
    assert "scripted: learner finished (exit code 0)" in drv.out.getvalue()


def test_all_wave_zero_members_done_ends_a_run_without_an_ending_member(tmp_path):
    plain = [ServiceSpec("a", ["a"]), ServiceSpec("b", ["b"]), ServiceSpec("router", ["r"], stop_wave=1)]
    drv = Scripted(plain, tmp_path, {"a": (1, 0), "b": (2, 0)})
    assert drv.run(install_signals=False) == 0
    assert rows(tmp_path)[-1]["message"] == "all services finished"


def test_a_give_up_is_exit_1_and_on_finish_is_not_called(tmp_path):
    drv = Scripted(specs(), tmp_path, {}, give_up_at=2)
    board = Board()
    assert drv.run(lambda: board, lambda status: status.stop_run(), install_signals=False) == EXIT_GAVE_UP
    assert not board.stopped and board.closed
    assert rows(tmp_path)[-1] == {**rows(tmp_path)[-1], "code": EXIT_GAVE_UP, "message": "giving up: scripted"}
    assert "procs" in Scripted(specs(), tmp_path / "x", {}).summary()


def test_a_signal_ends_the_run_with_128_plus_signal(tmp_path):
    drv = Scripted(specs(), tmp_path, {})
    real_poll = drv.poll_members

    def poll_then_signal():
        real_poll()
        if drv.round == 2:
            os.kill(os.getpid(), signal.SIGTERM)   # caught by the driver's handler

    drv.poll_members = poll_then_signal
    before = signal.getsignal(signal.SIGTERM)
    assert drv.run(install_signals=True) == 128 + signal.SIGTERM
    assert signal.getsignal(signal.SIGTERM) is before      # the handler is given back
    assert [r for r in rows(tmp_path) if r["event"] == "shutdown"][0]["reason"] == "SIGTERM"


def test_an_error_in_the_placement_is_recorded_and_raised(tmp_path):
    drv = Scripted(specs(), tmp_path, {})

    def broken():
        raise RuntimeError("the router never came up")

    drv.start = broken
    with pytest.raises(RuntimeError, match="never came up"):
        drv.run(install_signals=False)
    last = rows(tmp_path)[-1]
    assert last["code"] == EXIT_GAVE_UP and last["message"] == "scripted error: the router never came up"


def test_duplicate_member_names_are_refused(tmp_path):
    with pytest.raises(ValueError, match="duplicate"):
        Scripted([ServiceSpec("a", ["a"]), ServiceSpec("a", ["b"])], tmp_path, {})
