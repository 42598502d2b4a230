"""deploy/ray_run.py and `sage suite --ray`: a run's services placed on a Ray
cluster (two nodes on this machine, ``ray.cluster_utils.Cluster``), a killed
actor restarted by Ray's restart policy, and a suite of Ray tasks that resumes
after an interrupt without recomputing a finished run.

The command-line checks need no cluster (and most not even Ray); the cluster
tests are skipped when Ray (the optional extra ``.[cluster]``) is not installed.
The cluster's nodes listen on this machine's address, not 127.0.0.1: Ray 2.60
does not let a separate driver process join a loopback-only cluster. The Zenoh
router of the run still listens on 127.0.0.1, which both nodes share."""
from __future__ import annotations

import importlib.util
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).parent))
from test_supervisor import alive, wait_for  # noqa: E402

from deploy.ray_run import RayPlacement, parse_resources  # noqa: E402
from sage.cli import main  # noqa: E402

PY = sys.executable
ROOT = Path(__file__).resolve().parents[1]
HAVE_RAY = importlib.util.find_spec("ray") is not None
needs_ray = pytest.mark.skipif(not HAVE_RAY, reason="ray is not installed (pip install -e '.[cluster]')")


def processes_mentioning(text: str) -> list[int]:
    """Live processes whose command line contains ``text``."""
    out = []
    for proc in Path("/proc").iterdir():
        if proc.name.isdigit() and int(proc.name) != os.getpid():
            try:
                cmdline = (proc / "cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace")
            except OSError:
                continue
            if text in cmdline and alive(int(proc.name)):
                out.append(int(proc.name))
    return out


# ------------------------------------------------------------------ no cluster needed
def test_placement_requests_and_resource_flags():
    res = parse_resources(["actor=node_b:0.5", "actor-1=fast:1,GPU:1", "learner=big"])
    assert res == {"actor": {"node_b": 0.5}, "actor-1": {"fast": 1.0, "GPU": 1.0}, "learner": {"big": 1.0}}
    p = RayPlacement(resources=res)
    assert p.request("actor-1") == {"num_cpus": 1.0, "num_gpus": 1.0, "resources": {"node_b": 0.5, "fast": 1.0}}
    assert p.request("actor-0") == {"num_cpus": 1.0, "resources": {"node_b": 0.5}}
    assert p.request("router") == {"num_cpus": 0.0, "resources": {}}
    assert p.request("shield-1")["num_cpus"] == 1.0
    for bad in ("actor", "=x:1", "actor=x:abc", "actor=x:0", "actor=x:-1"):
        with pytest.raises(ValueError):
            parse_resources([bad])


def test_nothing_imports_ray_until_asked():
    code = "import sys, sage.cli, sage.suite, deploy.ray_run; assert 'ray' not in sys.modules, 'ray imported'"
    subprocess.run([PY, "-c", code], cwd=ROOT, check=True, timeout=120)


@pytest.mark.parametrize("argv, names", [
    ("train --ray 127.0.0.1:1", "no Ray cluster answers"),
    ("train --ray bogus", "HOST:PORT"),
    ("train --ray ray://head:10001", "Ray Client"),
    ("train --mode supervised --ray auto", "--mode ray"),
    ("train --ray-resources actor=x:1", "--ray-resources"),
    ("train --ray 127.0.0.1:1 --ray-resources actor=x:abc", "'abc'"),
    ("up --ray 127.0.0.1:1", "no Ray cluster answers"),
    ("up --ray-resources actor=x:1", "--ray ADDRESS"),
    ("suite --ray 127.0.0.1:1", "no Ray cluster answers"),
])
def test_bad_ray_input_is_one_line_and_exit_2(argv, names, tmp_path, capsys, monkeypatch):
    """Checked before anything is written; an address that needs a cluster to refuse
    it says so with Ray installed, and without Ray (the README's test command installs
    only ``.[test]``) says how to get Ray: the same one line and exit 2 either way."""
    if names == "no Ray cluster answers" and not HAVE_RAY:
        names = "Ray is not installed"
    monkeypatch.chdir(tmp_path)
    extra = ["--out", str(tmp_path / "s")] if argv.startswith("suite") else ["--run-dir", str(tmp_path / "r")]
    with pytest.raises(SystemExit) as exc:
        main(argv.split() + extra)
    assert exc.value.code == 2
    err = capsys.readouterr().err
    lines = [line for line in err.splitlines() if line.strip()]
    assert len(lines) == 1 and names in lines[0] and "Traceback" not in err, err
    assert not (tmp_path / "r").exists() and not (tmp_path / "s").exists()   # nothing written


@pytest.mark.parametrize("argv", ["train --ray auto", "up --ray auto", "suite --ray auto"])
def test_without_ray_installed_the_flags_say_how_to_get_it(argv, tmp_path, capsys, monkeypatch):
    monkeypatch.setitem(sys.modules, "ray", None)   # `import ray` raises ImportError
    monkeypatch.chdir(tmp_path)
    extra = ["--out", str(tmp_path / "s")] if argv.startswith("suite") else ["--run-dir", str(tmp_path / "r")]
    with pytest.raises(SystemExit) as exc:
        main(argv.split() + extra)
    assert exc.value.code == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "Ray is not installed" in err and ".[cluster]" in err, err


# ------------------------------------------------------------------ a two-node cluster
@pytest.fixture(scope="module")
def cluster():
    """Two Ray nodes on this machine, 3 logical CPUs each (resources are logical: a
    run's 5 services fit on 2 real cores), told apart by a custom resource."""
    if not HAVE_RAY:
        pytest.skip("ray is not installed (pip install -e '.[cluster]')")
    from ray.cluster_utils import Cluster

    small = {"object_store_memory": 80 * 1024**2}
    c = Cluster(initialize_head=True, head_node_args={"num_cpus": 3, "resources": {"node_a": 1},
                                                      "include_dashboard": False, **small})
    c.add_node(num_cpus=3, resources={"node_b": 1}, **small)
    c.wait_for_nodes()
    nodes = {"node_a": c.head_node.node_id, "node_b": c.list_all_nodes()[1].node_id}
    yield c.address, nodes
    c.shutdown()


def _status(run: Path) -> dict:
    try:
        return json.loads((run / "status.json").read_text())
    except (FileNotFoundError, json.JSONDecodeError):
        return {}


def _events(run: Path, kind: str, service: str) -> list[dict]:
    path = run / "supervisor.jsonl"
    rows = [json.loads(x) for x in path.read_text().splitlines()] if path.exists() else []
    return [r for r in rows if r["event"] == kind and r.get("service") == service]


def _rows(run: Path) -> int:
    try:
        return len((run / "metrics.jsonl").read_text().splitlines())
    except FileNotFoundError:
        return 0


@needs_ray
@pytest.mark.slow
@pytest.mark.timeout(300)
def test_train_on_two_nodes_survives_a_killed_actor(cluster, tmp_path):
    address, nodes = cluster
    run = tmp_path / "run"
    argv = [PY, "-m", "sage", "train", "--mode", "ray", "--ray", address,
            "--ray-resources", "actor-0=node_a:0.01", "--ray-resources", "actor-1=node_b:0.01",
            "--actors", "2", "--method", "happo_cbf", "--updates", "150", "--envs-per-actor", "2",
            "--chunk-len", "32", "--eval-episodes", "0", "--metrics-port", "0", "--run-dir", str(run),
            "--set", "algo.epochs=1", "--set", "algo.minibatches=1", "--set", "algo.critic_hidden=32"]
    proc = subprocess.Popen(argv, cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    try:
        wait_for(lambda: _rows(run) >= 2, 150, "two learner updates")
        services = _status(run)["services"]
        # each actor on the node its custom resource names: two different Ray nodes
        assert services["actor-0"]["node"] == nodes["node_a"] and services["actor-1"]["node"] == nodes["node_b"]
        assert services["learner"]["node"] == services["router"]["node"]   # on the driver's node
        victim = services["actor-1"]["pid"]
        os.kill(victim, signal.SIGKILL)
        new_pid = wait_for(lambda: [e["pid"] for e in _events(run, "start", "actor-1") if e["pid"] != victim],
                           60, "Ray to restart actor-1")[-1]
        # the restarted actor reaches the learner again (its heartbeat, through the router)
        wait_for(lambda: _status(run).get("status", {}).get("members", {}).get("actor/1", {}).get("pid") == new_pid,
                 60, "the restarted actor's heartbeat")
        out, _ = proc.communicate(timeout=180)
    finally:
        if proc.poll() is None:
            proc.send_signal(signal.SIGINT)
            proc.communicate(timeout=60)
    assert proc.returncode == 0, out
    assert json.loads(out.strip().splitlines()[-1])["updates"] == 150
    (crash,) = _events(run, "exit", "actor-1")[:1]
    assert crash["pid"] == victim and crash["code"] == -signal.SIGKILL
    assert _events(run, "restart", "actor-1") and not _events(run, "give_up", "actor-1")
    services = _status(run)["services"]
    assert services["actor-1"]["starts"] == 2 and services["actor-1"]["node"] == nodes["node_b"]
    assert all(s["starts"] == 1 for name, s in services.items() if name != "actor-1")
    log = (run / "logs" / "actor-1.log").read_text()
    assert f"(pid {victim}) exited with code -9; Ray restarts it" in log and f"restarted as pid {new_pid}" in log
    assert "ray: learner finished (exit code 0)" in out
    rows = [json.loads(x) for x in (run / "metrics.jsonl").read_text().splitlines()]
    assert [r["version"] for r in rows] == sorted(r["version"] for r in rows) and rows[-1]["update"] == 150
    starts = [e["pid"] for name in services for e in _events(run, "start", name)]
    assert len(starts) == 6 and not [pid for pid in starts if alive(pid)]   # nothing outlives the run


@needs_ray
@pytest.mark.slow
@pytest.mark.timeout(300)
def test_suite_on_ray_resumes_without_recomputing(cluster, tmp_path):
    address, _ = cluster
    out_dir = tmp_path / "suite"
    argv = [PY, "-m", "sage", "suite", "--ray", address, "--methods", "happo,sage", "--scenarios", "narrow_gate",
            "--seeds", "0,1", "--updates-per-run", "20", "--eval-episodes", "1", "--envs-per-actor", "2",
            "--set", "train.chunk_len=16", "--set", "env.max_steps=20", "--workers", "1", "--out", str(out_dir)]
    results = lambda: sorted(out_dir.glob("*__*.json"))   # noqa: E731
    first = subprocess.Popen(argv, cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    try:
        wait_for(results, 150, "a first finished run")
    finally:
        first.send_signal(signal.SIGINT)
        out1, _ = first.communicate(timeout=60)
    assert first.returncode == 128 + signal.SIGINT, out1
    assert "suite: interrupted;" in out1
    kept = {p.name: (p.stat().st_mtime_ns, p.read_bytes()) for p in results()}
    assert 1 <= len(kept) < 4, out1
    time.sleep(1.0)
    assert not processes_mentioning(str(out_dir / "runs")), "an interrupted run outlived the suite"

    second = subprocess.run(argv, cwd=ROOT, capture_output=True, text=True, timeout=240)
    assert second.returncode == 0, second.stdout + second.stderr
    log = second.stdout   # the suite's event lines (the progress bar goes to stderr)
    assert f"suite: {len(kept)} done, {4 - len(kept)} to run" in log and "finished runs are kept, not rerun" in log
    assert len(results()) == 4
    for name, (mtime, content) in kept.items():   # never recomputed
        path = out_dir / name
        assert path.stat().st_mtime_ns == mtime and path.read_bytes() == content
        assert f"suite: {name[:-5]} SR=" not in log
    for path in results():
        record = json.loads(path.read_text())
        assert record["budget"]["updates"] == 20 and record["eval"]["episodes"] >= 1
