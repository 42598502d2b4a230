"""Real multi-host faults (issue 32): router, shield, learner and two actors in
separate network namespaces joined to the router's by veth pairs, over the TLS
profile (per-actor certificates), with addresses from the benchmarking range
198.18.0.0/15 only. Faults use what this kernel has (no netem): actor 1's link
is taken down for 10 s (a partition), and actor 0 reaches the router through a
user-space TCP proxy that adds 200 ms each way and cuts its connections at
random. The run must reach its budget with 0 unfiltered steps and its chunk
accounting reconciled. Skipped where namespaces cannot be made (not root, no
`ip`, no openssl)."""
from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import pytest

from common.checkpoint import load_latest
from services.config import TrainConfig, TransportConfig

ROOT = Path(__file__).resolve().parents[1]
PY = sys.executable
PREFIX = f"sg{os.getpid() % 10000}"
HOSTS = ("router", "shield", "learner", "a0", "a1")
IN_SEQUENCE = ("used", "stale", "incarnation", "shape", "future", "overflow", "lost", "unused_restart")

PROXY = r'''
import random, socket, sys, threading, time
listen, target, delay, cut_s = sys.argv[1], sys.argv[2], float(sys.argv[3]), float(sys.argv[4])
lh, lp = listen.rsplit(":", 1); th, tp = target.rsplit(":", 1)
srv = socket.socket(); srv.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1); srv.bind((lh, int(lp))); srv.listen(16)
print("proxy up", flush=True)
rng = random.Random(0)
def pump(a, b, born):
    try:
        while True:
            data = a.recv(65536)
            if not data or time.monotonic() - born > cut_s:
                break
            time.sleep(delay)
            b.sendall(data)
    except OSError:
        pass
    for s in (a, b):
        try: s.shutdown(socket.SHUT_RDWR); s.close()
        except OSError: pass
while True:
    c, _ = srv.accept()
    u = socket.create_connection((th, int(tp)))
    born = time.monotonic() - rng.uniform(0, cut_s / 2)   # each connection lives a random 0.5-1x cut_s
    for a, b in ((c, u), (u, c)):
        threading.Thread(target=pump, args=(a, b, born), daemon=True).start()
'''


def _sh(*args: str, check: bool = True) -> subprocess.CompletedProcess:
    return subprocess.run(list(args), capture_output=True, text=True, check=check, timeout=30)


def _ns(host: str) -> str:
    return f"{PREFIX}{host}"


def _addr(k: int, side: int) -> str:
    """Pair k (host k+1 to the router): router side .4k+1, host side .4k+2, a /30 in 198.18.0.0/15."""
    return f"198.18.0.{4 * k + side}"


@pytest.fixture
def netns():
    if os.geteuid() != 0 or shutil.which("ip") is None or shutil.which("openssl") is None:
        pytest.skip("needs root, iproute2 and openssl for network namespaces")
    made = []
    try:
        for h in HOSTS:
            r = _sh("ip", "netns", "add", _ns(h), check=False)
            if r.returncode != 0:
                pytest.skip(f"cannot make a network namespace: {r.stderr.strip()}")
            made.append(_ns(h))
            _sh("ip", "-n", _ns(h), "link", "set", "lo", "up")
        for k, h in enumerate(HOSTS[1:]):
            vr, vh = f"{PREFIX}r{k}", f"{PREFIX}h{k}"
            _sh("ip", "link", "add", vr, "netns", _ns("router"), "type", "veth", "peer", "name", vh, "netns", _ns(h))
            _sh("ip", "-n", _ns("router"), "addr", "add", f"{_addr(k, 1)}/30", "dev", vr)
            _sh("ip", "-n", _ns(h), "addr", "add", f"{_addr(k, 2)}/30", "dev", vh)
            _sh("ip", "-n", _ns("router"), "link", "set", vr, "up")
            _sh("ip", "-n", _ns(h), "link", "set", vh, "up")
        yield {h: k for k, h in enumerate(HOSTS[1:])}
    finally:
        for n in made:
            _sh("ip", "netns", "del", n, check=False)


def _spawn(host: str, argv: list[str], log: Path) -> subprocess.Popen:
    return subprocess.Popen(["ip", "netns", "exec", _ns(host), *argv], cwd=ROOT, stdout=open(log, "w"),
                            stderr=subprocess.STDOUT, env=dict(os.environ, PYTHONPATH=str(ROOT)))


@pytest.mark.slow
@pytest.mark.timeout(600)
def test_partition_delay_and_cut_connections_across_namespaces(netns, tmp_path):
    from deploy import tls as dtls

    run = tmp_path / "run"
    certs = tmp_path / "certs"
    router_ips = [_addr(k, 1) for k in netns.values()]
    dtls.make_test_certs(certs, router_hosts=router_ips, actors=2)
    procs: list[subprocess.Popen] = []
    logs = tmp_path / "logs"
    logs.mkdir()
    try:
        procs.append(_spawn("router", [PY, "-m", "deploy.router", "--tls-certs", str(certs), "--run-id", "mh",
                                       "--actors", "2", *sum((["--listen", f"tls/{ip}:7447"] for ip in router_ips), [])],
                            logs / "router.log"))
        a0 = netns["a0"]   # actor 0 goes through the proxy, in the router's namespace, port 7448
        procs.append(_spawn("router", [PY, "-c", PROXY, f"{_addr(a0, 1)}:7448", f"{_addr(a0, 1)}:7447", "0.2", "6"],
                            logs / "proxy.log"))
        time.sleep(3)
        for host, role, extra in (("shield", "shield", []), ("learner", "learner", []),
                                  ("a0", "actor", ["--actor-id", "0"]), ("a1", "actor", ["--actor-id", "1"])):
            k = netns[host]
            port = 7448 if host == "a0" else 7447
            t = TransportConfig(mode="client", connect=[f"tls/{_addr(k, 1)}:{port}"], tls_root_ca=str(certs / "ca.pem"),
                                tls_cert=str(certs / "{role}.pem"), tls_key=str(certs / "{role}.key"),
                                tls_verify_name=host != "a0")   # through the proxy the name is the router's own
            cfg = TrainConfig(run_id="mh", run_dir=str(run), method="happo_cbf", actors=2, envs_per_actor=2,
                              chunk_len=4, updates=12, status_period_s=0.25, eval_episodes=0, checkpoint_every=2,
                              deploy_probe_every=0, transport=t,
                              algo={"epochs": 1, "minibatches": 1, "critic_hidden": 32}).resolve()
            path = tmp_path / f"{host}.json"
            path.write_text(cfg.to_json())
            procs.append(_spawn(host, [PY, "-m", f"services.{role}", "--config", str(path), *extra], logs / f"{host}.log"))
        learner = procs[3]

        def version() -> int:
            try:
                return json.loads((run / "learner_version.json").read_text())["version"]
            except (OSError, ValueError, KeyError):
                return -1

        deadline = time.monotonic() + 240
        while version() < 3 and time.monotonic() < deadline and learner.poll() is None:
            time.sleep(0.2)
        assert version() >= 3, (logs / "learner.log").read_text()[-3000:]
        link = f"{PREFIX}r{netns['a1']}"
        _sh("ip", "-n", _ns("router"), "link", "set", link, "down")   # partition actor 1 for 10 s
        time.sleep(10)
        _sh("ip", "-n", _ns("router"), "link", "set", link, "up")
        code = learner.wait(timeout=400)
        assert code == 0, (logs / "learner.log").read_text()[-3000:]
    finally:
        for p in procs:
            if p.poll() is None:
                p.terminate()
        for p in procs:
            try:
                p.wait(15)
            except subprocess.TimeoutExpired:
                p.kill()
    ck = load_latest(run / "checkpoints")
    assert ck["updates"] == 12 and ck["unfiltered_steps"] == 0
    c = ck["counts"]
    assert c["duplicate"] == c["seq_jump"] == 0
    accounted = sum(n + 1 for n in ck["last_seq"].values())
    assert sum(c[k] for k in IN_SEQUENCE) == accounted, (c, ck["last_seq"])
    print(json.dumps({"counts": c, "last_seq": ck["last_seq"]}))
