"""The live decision stream (issue: trees a person can read): actors publish
thinned decision traces on sage/<run>/trace/<actor>, the wire validates them,
LiveOccupancy turns them into per-carrier leaf occupancy and a correction
rate, and `sage watch` shows them from a real router."""
import os
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).parent))
from services_fakes import FakeBatchEnv, FakeMethod, fake_propose, fake_solve  # noqa: E402
from test_services import make_cfg, wait_for  # noqa: E402

from common import keys, wire  # noqa: E402
from common.audit.live import LiveOccupancy  # noqa: E402
from common.transport import Bus  # noqa: E402
from deploy.supervisor import free_tcp_port  # noqa: E402
from services.actor.service import ActorService  # noqa: E402
from services.config import ActorConfig  # noqa: E402
from services.shield.service import ShieldService  # noqa: E402


def trace_body(leaf, corr, version=3, depth=2):
    leaf = np.asarray(leaf, np.int32)
    K, N = leaf.shape
    return {"actor_id": 0, "version": version, "env_steps": 10, "every": 5, "leaf": leaf,
            "nodes": np.zeros((K, N, depth), np.int32), "sides": np.zeros((K, N, depth), bool),
            "correction_norm": np.asarray(corr, np.float64)}


def test_trace_round_trips_and_a_bad_one_is_rejected_by_reason():
    body = trace_body([[0, 1, 2], [3, 3, 0]], [0.0, 0.2])
    msg = wire.decode(wire.encode("trace", body, run_id="r", sender="actor/0", seq=1), run_id="r", expect="trace")
    np.testing.assert_array_equal(msg.body["leaf"], body["leaf"])
    bad = dict(body, correction_norm=np.zeros(3))   # K = 2 in leaf, 3 here
    with pytest.raises(wire.WireError) as e:
        wire.decode(wire.encode("trace", bad, run_id="r", sender="actor/0", seq=2), run_id="r", expect="trace")
    assert e.value.reason == "shape"


def test_live_occupancy_counts_leaves_and_corrections_over_the_window():
    live = LiveOccupancy(window=2)
    live.add(trace_body([[0, 0, 0], [0, 0, 0]], [0.0, 0.0], version=1))   # falls out of the window
    live.add(trace_body([[0, 1, 3], [1, 1, 3]], [0.0, 0.5], version=2))
    live.add(trace_body([[2, 1, 3], [3, 1, 3]], [0.1, 0.0], version=3))
    occ = live.occupancy()
    assert occ.shape == (3, 4)
    np.testing.assert_allclose(occ[0], [0.25, 0.25, 0.25, 0.25])
    np.testing.assert_allclose(occ[1], [0, 1, 0, 0]) and np.testing.assert_allclose(occ[2], [0, 0, 0, 1])
    rate, mean = live.correction()
    assert rate == pytest.approx(0.5) and mean == pytest.approx(0.3)
    text = "\n".join(live.table())
    assert "100.0%" in text and "corrected 50.0%" in text and "0:v3" in text and live.traces == 3


@pytest.mark.parametrize("pipelined", [False, True], ids=["sync", "pipelined"])
def test_actor_publishes_one_trace_every_n_steps(tmp_path, pipelined):
    cfg = make_cfg(tmp_path, actors=1, chunk_len=1000, actor=ActorConfig(trace_every=3))
    bus, stop = Bus.open(inprocess=True), threading.Event()
    traces = []
    bus.subscribe(keys.trace_all(cfg.run_id),
                  lambda _k, p: traces.append(wire.decode(p, run_id=cfg.run_id, expect="trace").body))
    threading.Thread(target=ShieldService(cfg, bus, stop=stop, solve=fake_solve).run, daemon=True).start()
    env = [FakeBatchEnv(2), FakeBatchEnv(1, seed=1)] if pipelined else FakeBatchEnv(2)
    actor = ActorService(cfg, bus, 0, stop=stop, env=env, propose=fake_propose)
    th = threading.Thread(target=actor.run, daemon=True)
    th.start()
    wait_for(lambda: actor.state == "waiting")   # subscribed to parameters
    body = {"version": 4, "incarnation": "i", "method": cfg.method, "params": FakeMethod().policy_params(),
            "settings": {"kappa": 1.0}}
    bus.publish(keys.params(cfg.run_id), wire.encode("params", body, run_id=cfg.run_id, sender="learner/0", seq=0))
    try:
        wait_for(lambda: len(traces) >= 4, timeout=20)
        steps = actor.steps_taken
    finally:
        stop.set()
        th.join(5)   # before the session closes under it
        bus.close()
    assert steps // 3 - 1 <= len(traces) <= steps // 3 + 1
    K = 3 if pipelined else 2
    for t in traces:
        assert t["leaf"].shape == (K, 3) and t["every"] == 3 and t["version"] == 4
        assert (t["correction_norm"] >= 0).all()
    # the fake row a_0 >= 0.5 corrects most proposals: the stream shows it
    assert np.concatenate([t["correction_norm"] for t in traces]).max() > 0


def test_sage_watch_shows_the_table_from_a_router(tmp_path):
    from services.config import TrainConfig

    port = free_tcp_port()
    router = subprocess.Popen([sys.executable, "-m", "deploy.router", "--listen", f"tcp/127.0.0.1:{port}"],
                              stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    run = tmp_path / "run"
    cfg = TrainConfig(run_id="watched", run_dir=str(run), actor=ActorConfig(trace_every=5))
    cfg.transport.connect, cfg.transport.mode = [f"tcp/127.0.0.1:{port}"], "client"
    run.mkdir()
    cfg.save(run / "config.json")
    pub = None
    try:
        time.sleep(1.0)
        pub = Bus.open(connect=cfg.transport.connect, mode="client")
        stop = threading.Event()

        def feed():
            n = 0
            while not stop.is_set():
                body = trace_body([[n % 4, 1, 2]], [0.2 if n % 2 else 0.0], depth=4)   # the run's depth
                pub.publish(keys.trace("watched", 0), wire.encode("trace", body, run_id="watched",
                                                                  sender="actor/0", seq=n))
                pub.publish(keys.trace("watched", 1), b"\x93forged")   # rejected and counted
                n += 1
                stop.wait(0.02)

        th = threading.Thread(target=feed, daemon=True)
        th.start()
        env = dict(os.environ, PYTHONUNBUFFERED="1")
        r = subprocess.run([sys.executable, "-m", "sage.cli", "watch", str(run), "--seconds", "3", "--period", "0.5"],
                           capture_output=True, text=True, timeout=60, env=env)
        stop.set()
        th.join(5)
    finally:
        if pub is not None:
            pub.close()
        router.terminate()
        router.wait(10)
    assert r.returncode == 0, r.stderr
    assert "leaf 3" in r.stdout and "QP corrected" in r.stdout and "rejected trace messages" in r.stdout
    assert "leaf 16" not in r.stdout and "ended" not in r.stdout
    assert r.stdout.count("run watched") >= 3   # one table per period, whole blocks when not a terminal


def test_live_occupancy_refuses_traces_that_cannot_be_the_runs_trees():
    live = LiveOccupancy(window=10, depth=2)
    live.add(trace_body([[0, 1, 3]], [0.1]))
    for bad in (trace_body([[10**6, 0, 0]], [0.0]),            # leaf far outside 0..3
                trace_body([[0, -1, 0]], [0.0]),
                trace_body([[0, 1, 3]], [0.0], depth=3),        # not this run's depth
                trace_body([[0, 1, 3]], [np.nan]), trace_body([[0, 1, 3]], [-1.0])):
        with pytest.raises(ValueError):
            live.add(bad)
    live.add(trace_body([[3, 2, 1]], [0.0]))                    # good input is still kept
    assert live.traces == 2 and live.occupancy().shape == (3, 4)
    with pytest.raises(ValueError):
        LiveOccupancy().add(trace_body([[0, 0, 0]], [0.0], depth=40))   # 2^40 leaf columns


def _watch(run, *extra, timeout=60):
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    return subprocess.run([sys.executable, "-m", "sage.cli", "watch", str(run), *extra],
                          capture_output=True, text=True, timeout=timeout, env=env)


def _watched_run(tmp_path, port):
    from services.config import TrainConfig

    run = tmp_path / "run"
    cfg = TrainConfig(run_id="watched", run_dir=str(run), actor=ActorConfig(trace_every=5))
    cfg.transport.connect, cfg.transport.mode = [f"tcp/127.0.0.1:{port}"], "client"
    run.mkdir()
    cfg.save(run / "config.json")
    return run


def _one_line(r, *words):
    lines = [x for x in r.stderr.splitlines() if x.strip()]
    assert r.returncode == 2 and len(lines) == 1 and "Traceback" not in r.stderr, r.stderr
    for w in words:
        assert w in lines[0], lines[0]


def test_sage_watch_bad_endpoint_and_finished_run_are_one_line_and_exit_2(tmp_path):
    import json

    run = _watched_run(tmp_path, free_tcp_port())   # nothing listens there: the run is gone
    _one_line(_watch(run, "--connect", "bogus", "--seconds", "5"), "cannot reach", "bogus")
    _one_line(_watch(run, "--seconds", "5"), "cannot reach", "has the run ended")
    # a supervised run that finished: its supervisor said so in supervisor.jsonl
    events = [{"t": 1.0, "event": "supervisor_start"},
              {"t": 2.0, "event": "supervisor_exit", "code": 0, "message": "learner finished"}]
    (run / "supervisor.jsonl").write_text("".join(json.dumps(e) + "\n" for e in events))
    _one_line(_watch(run, "--seconds", "5"), "the run has ended", "learner finished")


@pytest.mark.parametrize("how", ["supervisor", "learner"])
def test_sage_watch_says_the_run_ended_and_exits_0(tmp_path, how):
    import json

    port = free_tcp_port()
    router = subprocess.Popen([sys.executable, "-m", "deploy.router", "--listen", f"tcp/127.0.0.1:{port}"],
                              stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    run = _watched_run(tmp_path, port)
    (run / "supervisor.jsonl").write_text(json.dumps({"t": 1.0, "event": "supervisor_start"}) + "\n")
    pub, watch = None, None
    ended = threading.Event()
    try:
        time.sleep(1.0)
        pub = Bus.open(connect=[f"tcp/127.0.0.1:{port}"], mode="client")
        stop = threading.Event()

        def feed():
            n = 0
            while not stop.is_set():
                pub.publish(keys.trace("watched", 0), wire.encode(
                    "trace", trace_body([[n % 4, 1, 2]], [0.0], depth=4), run_id="watched", sender="actor/0", seq=n))
                if ended.is_set() and how == "learner":   # the learner's last heartbeats: done
                    body = {"role": "learner", "id": "0", "state": "done", "pid": 1, "uptime_s": 1.0, "version": 9,
                            "env_steps": 10, "env_steps_per_s": 0.0, "updates": 9, "success_rate": None,
                            "shield_p99_s": None, "message": "", "extra": {}}
                    pub.publish(keys.status("watched", "learner", 0), wire.encode(
                        "status", body, run_id="watched", sender="learner/0", seq=n))
                n += 1
                stop.wait(0.02)

        th = threading.Thread(target=feed, daemon=True)
        th.start()
        watch = subprocess.Popen([sys.executable, "-m", "sage.cli", "watch", str(run), "--seconds", "45",
                                  "--period", "0.3"], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                                 env=dict(os.environ, PYTHONUNBUFFERED="1"))
        seen = []
        for line in watch.stdout:   # the live table first ...
            seen.append(line)
            if "leaf 3" in line:
                break
        # ... then the run ends: its supervisor exits, or the learner reports it is done
        if how == "supervisor":
            with open(run / "supervisor.jsonl", "a") as f:
                f.write(json.dumps({"t": time.time(), "event": "supervisor_exit", "code": 0,
                                    "message": "learner finished"}) + "\n")
        ended.set()
        out, err = watch.communicate(timeout=60)
        stop.set()
        th.join(5)
    finally:
        if watch is not None and watch.poll() is None:
            watch.kill()
            watch.communicate()
        if pub is not None:
            pub.close()
        router.terminate()
        router.wait(10)
    assert watch.returncode == 0, err
    assert any("leaf 3" in x for x in seen)   # it showed the live table until then
    last = out.strip().splitlines()[-1]
    assert last.startswith("run watched ended (") and ("learner finished" if how == "supervisor" else "done") in last


def test_a_table_that_stopped_moving_says_so():
    from sage.watch import stale_note

    assert stale_note(None, 1.0) == "" and stale_note(2.0, 1.0) == "" and stale_note(5.0, 1.0) == ""
    assert stale_note(12.4, 1.0) == "  (no new trace for 12 s)"
    assert stale_note(12.4, 5.0) == ""   # within three redraw periods
