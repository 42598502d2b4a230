"""Output that fits where it goes: the live status line and the progress bar
rewrite one terminal line in place, and write plain periodic lines elsewhere."""
import io

import pytest

from common.status import LiveLine, Progress, format_duration


class Stream(io.StringIO):
    def __init__(self, tty: bool):
        super().__init__()
        self.tty = tty

    def isatty(self) -> bool:
        return self.tty


class Clock:
    def __init__(self, t: float = 100.0):
        self.t = t

    def __call__(self) -> float:
        return self.t


def test_liveline_off_a_terminal_prints_one_plain_line_per_period():
    out, clock = Stream(tty=False), Clock()
    live = LiveLine(out, log_period_s=10.0, clock=clock)
    for k in range(61):            # 60 s of calls, one every second
        live.show(f"line {k}")
        clock.t += 1.0
    lines = out.getvalue().splitlines()
    assert lines == [f"line {k}" for k in range(0, 61, 10)]   # the first at once, then one per 10 s
    assert "\r" not in out.getvalue()
    live.close("final")
    assert out.getvalue().splitlines()[-1] == "final"


def test_liveline_on_a_terminal_rewrites_in_place_on_every_call():
    out, clock = Stream(tty=True), Clock()
    live = LiveLine(out, log_period_s=10.0, clock=clock)
    for k in range(3):
        live.show(f"line {k}")
    assert out.getvalue() == "".join(f"\rline {k}   " for k in range(3))
    assert "\n" not in out.getvalue()
    live.close("done")
    assert out.getvalue().endswith("\rdone\n")


def test_progress_off_a_terminal_prints_plain_lines_per_period_and_a_final_one():
    out, clock = Stream(tty=False), Clock()
    bar = Progress(out, 10, "suite", unit="runs", log_period_s=10.0, clock=clock)
    for k in range(25):            # 25 s, one update a second
        bar.update(k // 3, running=2, failed=0)
        clock.t += 1.0
    lines = out.getvalue().splitlines()
    assert len(lines) == 2 and "\r" not in out.getvalue()          # at 10 s and at 20 s; none at once
    assert lines[0].startswith("suite:  30% 3/10 runs, 2 running | 10s elapsed, ETA ")
    bar.update(10, running=0)
    bar.close()
    assert out.getvalue().splitlines()[-1].startswith("suite: 100% 10/10 runs, 0 running | 25s elapsed, ETA 0s")


def test_progress_of_a_short_job_off_a_terminal_prints_nothing():
    out, clock = Stream(tty=False), Clock()
    bar = Progress(out, 4, "sage eval", unit="episodes", clock=clock)
    bar.update(2)
    clock.t += 3.0
    bar.update(4)
    bar.close()
    assert out.getvalue() == ""


def test_progress_on_a_terminal_is_a_bar_rewritten_in_place():
    out, clock = Stream(tty=True), Clock()
    bar = Progress(out, 4, "suite", unit="runs", width=8, tty_period_s=0.5, clock=clock)
    bar.update(0, running=2)
    assert out.getvalue() == "\rsuite [--------] 0/4 runs, 2 running | 0s elapsed, ETA -"
    clock.t += 0.1
    bar.update(0, running=2)                      # nothing new, within the period: no rewrite
    assert out.getvalue().count("\r") == 1
    clock.t += 59.9
    bar.update(1, running=2, failed=1)            # the counts changed: rewritten at once
    last = out.getvalue().rsplit("\r", 1)[1]
    # 2 of 4 ended; the ETA is the mean time per finished run times the runs left
    assert last.startswith("suite [####----] 1/4 runs, 2 running, 1 failed | 1m00s elapsed, ETA 2m00s")
    assert "\n" not in out.getvalue()
    bar.clear()                                   # before another line goes to the terminal
    assert out.getvalue().endswith(last + "\r" + " " * len(last) + "\r")
    bar.update(1, running=2, failed=1, eta_s=42.0)  # redrawn after a clear, with the caller's ETA
    assert out.getvalue().rsplit("\r", 1)[1].endswith("ETA 42s")
    bar.update(3, running=0, failed=1)
    bar.close()
    assert out.getvalue().endswith("\n") and "[########] 3/4 runs, 0 running, 1 failed" in out.getvalue()


def test_progress_rewrite_pads_over_a_longer_previous_line():
    out, clock = Stream(tty=True), Clock()
    bar = Progress(out, 2, "x", clock=clock)
    bar.update(0, note="a long note here")
    first = out.getvalue()[1:]
    bar.update(1)
    second = out.getvalue()[1 + len(first) + 1:]
    assert len(second) >= len(first)


@pytest.mark.parametrize("s, text", [(None, "-"), (float("nan"), "-"), (0.4, "0s"), (59, "59s"),
                                     (185, "3m05s"), (7440, "2h04m")])
def test_format_duration(s, text):
    assert format_duration(s) == text


def test_suite_eta_from_the_mean_run_time():
    from sage.suite import suite_eta

    assert suite_eta(None, 3, [], 2) is None                    # no run finished yet
    assert suite_eta(60.0, 0, [], 2) == 0.0
    # 2 workers busy for 10 s and 50 s of a 60 s mean, 3 queued: 50, 10 -> 10+60=70, 50+60=110, 70+60=130
    assert suite_eta(60.0, 3, [50.0, 10.0], 2) == pytest.approx(130.0)
    assert suite_eta(60.0, 1, [90.0], 1) == pytest.approx(60.0)  # an overdue run counts as ending now
