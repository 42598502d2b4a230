"""Secure deployment profile (deploy/tls.py, deploy/router.py --tls-certs):
a real router process with mutual TLS and per-role access control, and real
client sessions holding the role certificates (CN = role).

Denials are checked against a positive control sent afterwards on the same
path (a legitimate message must arrive before the test concludes that a
forged one did not), so a slow machine cannot turn a lost message into a pass.
Everything is on 127.0.0.1, on free ports, with bounded waits.
"""
from __future__ import annotations

import queue
import shutil
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest
import zenoh

from common import keys
from common.metrics_prom import serve_metrics
from common.transport import Bus, TlsFiles, tls_link_config, zenoh_config
from deploy import tls as dtls
from deploy.supervisor import free_tcp_port
from services.config import PortsConfig, TransportConfig
from conftest import wait_for  # noqa: E402

pytestmark = [pytest.mark.timeout(120),
              pytest.mark.skipif(shutil.which("openssl") is None, reason="needs the openssl CLI for test certificates")]

ROOT = Path(__file__).resolve().parents[1]
RUN = "tlsrun"


class Inbox:
    """Subscriber callback target: (key suffix, payload) pairs."""

    def __init__(self):
        self.items: list[tuple[str, bytes]] = []
        self._lock = threading.Lock()

    def __call__(self, key: str, payload: bytes) -> None:
        with self._lock:
            self.items.append((key.split("/", 2)[2], payload))

    def payloads(self) -> list[bytes]:
        with self._lock:
            return [p for _, p in self.items]


@pytest.fixture(scope="module")
def pki(tmp_path_factory):
    d = tmp_path_factory.mktemp("pki")
    files = dtls.make_test_certs(d / "certs")
    ca = (files["ca"], files["ca_key"])
    dtls.make_cert(d / "certs", "intruder", ca)   # right CA, a CN no policy names
    rogue = dtls.make_ca(d / "rogue", cn="rogue-ca")
    dtls.make_cert(d / "rogue", "learner", rogue)  # right CN, wrong CA
    return d


@pytest.fixture(scope="module")
def router(pki):
    port = free_tcp_port()
    endpoint = f"tls/127.0.0.1:{port}"
    proc = subprocess.Popen([sys.executable, "-m", "deploy.router", "--tls-certs", str(pki / "certs"),
                             "--run-id", RUN, "--listen", endpoint],
                            cwd=ROOT, stderr=subprocess.PIPE, stdout=subprocess.DEVNULL, text=True)
    lines: queue.Queue[str] = queue.Queue()
    threading.Thread(target=lambda: [lines.put(x) for x in proc.stderr], daemon=True).start()
    try:
        line = lines.get(timeout=30)
    except queue.Empty:
        proc.kill()
        raise AssertionError("router did not start within 30 s")
    assert "listening" in line, line
    yield {"endpoint": endpoint, "port": port, "certs": pki / "certs", "rogue": pki / "rogue"}
    proc.terminate()
    try:
        assert proc.wait(15) == 0
    finally:
        if proc.poll() is None:
            proc.kill()


@pytest.fixture
def open_bus(router):
    buses: list[Bus] = []

    def _open(role: str, certs: Path | None = None) -> Bus:
        d = Path(certs or router["certs"])
        tls = TlsFiles(str(router["certs"] / "ca.pem"), str(d / "{role}.pem"), str(d / "{role}.key"))
        bus = Bus.open(connect=[router["endpoint"]], mode="client", tls=tls, role=role)
        buses.append(bus)
        return bus

    yield _open
    for b in buses:
        b.close()


def all_replies(bus: Bus, key: str, timeout: float = 1.0) -> list[bytes]:
    """Every reply of every queryable (not just the first / best-matching one)."""
    return sorted(r.ok.payload.to_bytes() if r.ok is not None else b"ERR:" + r.err.payload.to_bytes()
                  for r in bus._session.get(key, payload=b"q", timeout=timeout, target=zenoh.QueryTarget.ALL))


def answer(q: "queue.Queue", payload: bytes, stop: threading.Event, seen: list | None = None) -> threading.Thread:
    def loop():
        while not stop.is_set():
            try:
                req = q.get(timeout=0.05)
            except queue.Empty:
                continue
            if seen is not None:
                seen.append(req.payload)
            req.reply(payload)

    t = threading.Thread(target=loop, daemon=True)
    t.start()
    return t


# ------------------------------------------------------------------- (a) who may connect
def test_client_without_valid_certificate_cannot_connect(router, open_bus):
    ep, certs = router["endpoint"], router["certs"]
    # Trusts the router (root CA) but presents no client certificate.
    cfg = zenoh_config(connect=[ep], mode="client")
    cfg.insert_json5("transport/link/tls", '{"root_ca_certificate": "%s"}' % (certs / "ca.pem"))
    with pytest.raises(zenoh.ZError, match="Unable to connect"):
        zenoh.open(cfg)
    # Plain TCP to the TLS port.
    with pytest.raises(zenoh.ZError, match="Unable to connect"):
        zenoh.open(zenoh_config(connect=[f"tcp/127.0.0.1:{router['port']}"], mode="client"))
    # CN "learner", but signed by another CA.
    with pytest.raises(zenoh.ZError, match="Unable to connect"):
        open_bus("learner", certs=router["rogue"])

    # A peer session (it opens without a router) with no certificate reaches nobody.
    actor = open_bus("actor")
    inbox = Inbox()
    actor.subscribe(keys.params(RUN), inbox)
    stranger = Bus(zenoh.open(zenoh_config(connect=[ep], mode="peer")))
    try:
        time.sleep(0.3)
        stranger.publish(keys.params(RUN), b"from-stranger")
        assert stranger.request(keys.shield(RUN), b"q", timeout=0.3) is None
    finally:
        stranger.close()
    learner = open_bus("learner")
    learner.publish(keys.params(RUN), b"control")
    wait_for(lambda: b"control" in inbox.payloads(), 5, "legitimate params")
    time.sleep(0.2)
    assert inbox.payloads() == [b"control"]


def test_certificate_with_unknown_common_name_gets_nothing(router, open_bus):
    """Right CA, CN "intruder": the link is up, default_permission deny drops everything."""
    actor, learner, shield = open_bus("actor"), open_bus("learner"), open_bus("shield")
    intruder = open_bus("intruder")
    inbox, spy = Inbox(), Inbox()
    actor.subscribe(keys.params(RUN), inbox)
    actor.subscribe(keys.control(RUN), inbox)
    intruder.subscribe(keys.traj_all(RUN), spy)
    stop = threading.Event()
    answer(shield.serve(keys.shield(RUN)), b"genuine", stop)
    try:
        time.sleep(0.3)
        intruder.publish(keys.params(RUN), b"intruder-params")
        intruder.publish(keys.control(RUN), b"intruder-stop")
        assert intruder.request(keys.shield(RUN), b"q", timeout=0.5) is None
        time.sleep(0.2)
        learner.publish(keys.params(RUN), b"legit")
        actor.publish(keys.traj(RUN, 0), b"chunk")
        wait_for(lambda: b"legit" in inbox.payloads(), 5, "legitimate params")
        time.sleep(0.3)
        assert inbox.payloads() == [b"legit"]
        assert spy.payloads() == []
    finally:
        stop.set()


# ------------------------------------------------------------------- (b) what an actor may not do
def test_actor_cannot_publish_parameters_or_control(router, open_bus):
    learner, actor, rogue_actor, supervisor = (open_bus("learner"), open_bus("actor"),
                                               open_bus("actor"), open_bus("supervisor"))
    params_in, control_in, status_in = Inbox(), Inbox(), Inbox()
    actor.subscribe(keys.params(RUN), params_in)
    actor.subscribe(keys.control(RUN), control_in)
    supervisor.subscribe(keys.status_all(RUN), status_in)
    time.sleep(0.3)
    rogue_actor.publish(keys.params(RUN), b"forged-params")
    rogue_actor.publish(keys.control(RUN), b"forged-stop")
    rogue_actor.publish(keys.status(RUN, "learner", 0), b"forged-learner-status")
    time.sleep(0.3)
    learner.publish(keys.params(RUN), b"legit-params")
    supervisor.publish(keys.control(RUN), b"legit-stop")
    rogue_actor.publish(keys.status(RUN, "actor", 1), b"own-status")
    wait_for(lambda: params_in.payloads() and control_in.payloads() and status_in.payloads(), 5,
             "legitimate params, control and status")
    time.sleep(0.3)
    assert params_in.payloads() == [b"legit-params"]
    assert control_in.payloads() == [b"legit-stop"]
    assert status_in.items == [("status/actor/1", b"own-status")]


def test_actor_cannot_answer_as_the_shield(router, open_bus):
    actor, rogue_actor, learner = open_bus("actor"), open_bus("actor"), open_bus("learner")
    stop = threading.Event()
    forged_seen: list[bytes] = []
    answer(rogue_actor.serve(keys.shield(RUN)), b"forged", stop, forged_seen)
    try:
        time.sleep(0.3)
        # Only the forged queryable exists: nobody answers.
        assert actor.request(keys.shield(RUN), b"q", timeout=1.0) is None
        # With the real shield up, every reply is the shield's.
        shield = open_bus("shield")
        answer(shield.serve(keys.shield(RUN)), b"genuine", stop)
        wait_for(lambda: actor.request(keys.shield(RUN), b"q", timeout=0.5) is not None, 5, "shield reply")
        assert all_replies(actor, keys.shield(RUN)) == [b"genuine"]
        assert actor.request(keys.shield(RUN), b"q", timeout=1.0).ok == b"genuine"
        # The learner has no business querying the shield.
        assert all_replies(learner, keys.shield(RUN), timeout=0.5) == []
        assert forged_seen == []   # not a single query was routed to the actor's queryable
    finally:
        stop.set()


# ------------------------------------------------------------------- (c) what must keep working
def test_legitimate_role_traffic_flows(router, open_bus):
    learner, actor, shield, supervisor = (open_bus("learner"), open_bus("actor"), open_bus("shield"),
                                          open_bus("supervisor"))
    a_params, a_control, l_traj, l_control, s_control, sup_status, a_heartbeat = (Inbox() for _ in range(7))
    actor.subscribe(keys.params(RUN), a_params)
    actor.subscribe(keys.status(RUN, "learner", 0), a_heartbeat)   # parameter fencing reads it
    actor.subscribe(keys.control(RUN), a_control)
    learner.subscribe(keys.traj_all(RUN), l_traj)
    learner.subscribe(keys.control(RUN), l_control)
    shield.subscribe(keys.control(RUN), s_control)
    supervisor.subscribe(keys.status_all(RUN), sup_status)
    stop = threading.Event()
    queries: list[bytes] = []
    answer(shield.serve(keys.shield(RUN)), b"action", stop, queries)
    try:
        time.sleep(0.3)
        learner.publish(keys.params(RUN), b"v1")
        actor.publish(keys.traj(RUN, 3), b"chunk")
        for role, bus in (("learner", learner), ("actor", actor), ("shield", shield)):
            bus.publish(keys.status(RUN, role, 0), role.encode())
        reply = actor.request(keys.shield(RUN), b"rows", timeout=5.0)
        assert reply is not None and reply.ok == b"action" and queries == [b"rows"]
        wait_for(lambda: a_params.payloads() and l_traj.payloads() and len(sup_status.items) == 3
                 and a_heartbeat.payloads(), 5, "params, traj, three status messages and the learner's at the actor")
        assert a_params.payloads() == [b"v1"]
        assert l_traj.items == [("traj/3", b"chunk")]
        assert sorted(sup_status.items) == [("status/actor/0", b"actor"), ("status/learner/0", b"learner"),
                                            ("status/shield/0", b"shield")]
        supervisor.publish(keys.control(RUN), b"stop")
        wait_for(lambda: a_control.payloads() and l_control.payloads() and s_control.payloads(), 5,
                 "control at every service")
    finally:
        stop.set()


def test_bus_from_transport_config(router):
    """The run config's fields, with the {role} placeholder, reach the router."""
    certs = router["certs"]
    t = TransportConfig(mode="client", connect=[router["endpoint"]], tls_root_ca=str(certs / "ca.pem"),
                        tls_cert=str(certs / "{role}.pem"), tls_key=str(certs / "{role}.key"))
    learner, actor = Bus.from_transport(t, role="learner"), Bus.from_transport(t, role="actor")
    try:
        inbox = Inbox()
        actor.subscribe(keys.params(RUN), inbox)
        time.sleep(0.3)
        learner.publish(keys.params(RUN), b"v")
        wait_for(lambda: inbox.payloads() == [b"v"], 5, "params over TLS")
    finally:
        learner.close()
        actor.close()


# ------------------------------------------------------------------- defaults unchanged, configs
def test_defaults_stay_plain_and_local(tmp_path):
    assert TlsFiles.from_transport(TransportConfig()) is None
    assert PortsConfig().bind == "127.0.0.1"
    cfg = zenoh_config(connect=["tcp/127.0.0.1:1"], mode="client")
    assert '"root_ca_certificate":null' in cfg.get_json("transport/link/tls").replace(" ", "")
    # In-process ignores TLS; the session opens with no network and works.
    bus = Bus.open(inprocess=True, tls=TlsFiles("/nonexistent/ca.pem", "/nonexistent/c.pem", "/nonexistent/k"))
    try:
        inbox = Inbox()
        bus.subscribe(keys.params(RUN), inbox)
        bus.publish(keys.params(RUN), b"local")
        wait_for(lambda: inbox.payloads() == [b"local"], 5, "in-process delivery")
    finally:
        bus.close()
    tls = TlsFiles(str(tmp_path / "ca.pem"), str(tmp_path / "c.pem"), str(tmp_path / "k.pem"))
    with pytest.raises(ValueError, match="not tls/"):
        zenoh_config(connect=["tcp/127.0.0.1:1"], mode="client", tls=tls)
    with pytest.raises(FileNotFoundError, match="root CA"):
        tls_link_config(tls)
    with pytest.raises(ValueError, match="all three"):
        tls_link_config(TlsFiles(root_ca=str(tmp_path / "ca.pem")))
    with pytest.raises(ValueError, match="no role"):
        TlsFiles("ca", "{role}.pem", "{role}.key").for_role(None)


def test_metrics_bind_loopback_by_default():
    from prometheus_client import CollectorRegistry

    server = serve_metrics(free_tcp_port(), CollectorRegistry())
    try:
        assert server.server_address[0] == "127.0.0.1"
    finally:
        server.shutdown()
        server.server_close()


def test_shipped_router_config_is_loopback():
    import json

    from deploy.router import router_config

    cfg = router_config()
    assert json.loads(cfg.get_json("listen/endpoints")) == ["tcp/127.0.0.1:7447"]


def test_access_control_matches_role_table(tmp_path):
    acl = dtls.access_control(RUN)
    assert acl["enabled"] is True and acl["default_permission"] == "deny"
    assert {s["id"]: s["cert_common_names"] for s in acl["subjects"]} == {r: [r] for r in dtls.ROLES}
    rules = {r["id"]: r for r in acl["rules"]}
    by_role = {p["subjects"][0]: [rules[i] for i in p["rules"]] for p in acl["policies"]}

    def allowed(role, message, flow):
        return sorted(k for r in by_role[role] if message in r["messages"] and flow in r["flows"]
                      for k in r["key_exprs"])

    root = f"sage/{RUN}"
    assert allowed("learner", "put", "ingress") == [f"{root}/params", f"{root}/status/learner/*"]
    assert allowed("actor", "put", "ingress") == [f"{root}/status/actor/*", f"{root}/trace/*", f"{root}/traj/*"]
    assert allowed("actor", "query", "ingress") == [f"{root}/shield/*"]
    assert allowed("actor", "declare_queryable", "ingress") == []
    assert allowed("actor", "reply", "ingress") == []
    assert allowed("shield", "declare_queryable", "ingress") == [f"{root}/shield/*"]
    assert allowed("shield", "reply", "ingress") == [f"{root}/shield/*"]
    assert allowed("supervisor", "put", "ingress") == [f"{root}/control", f"{root}/status/supervisor/*"]
    assert all(r["permission"] == "allow" for r in acl["rules"])
    # The written file is what zenoh parses.
    out = dtls.write_router_config(tmp_path / "r.json5", tmp_path, run_id=RUN, listen=["tls/127.0.0.1:7447"])
    parsed = zenoh.Config.from_file(str(out))
    assert '"enable_mtls":true' in parsed.get_json("transport/link/tls").replace(" ", "")
    with pytest.raises(ValueError, match="tls/"):
        dtls.secure_router_config(tmp_path, listen=["tcp/127.0.0.1:7447"])


def test_every_put_of_a_stream_is_delivered_through_access_control(router, open_bus):
    """zenoh 1.10 behind access control delivered only the first put of a declared
    publisher; TLS sessions therefore put directly (common/transport.py)."""
    got: list[bytes] = []
    sup = open_bus("supervisor")
    sup.subscribe(keys.status_all(RUN), lambda _k, p: got.append(p))
    learner = open_bus("learner")
    time.sleep(0.5)
    for i in range(20):
        learner.publish(keys.status(RUN, "learner", "0"), b"beat %d" % i)
        time.sleep(0.02)
    wait_for(lambda: len(got) >= 20, 10, "all 20 heartbeats")
    assert got == [b"beat %d" % i for i in range(20)]


@pytest.mark.slow
def test_supervised_run_over_tls_with_access_control_reaches_its_budget(pki, tmp_path):
    """`sage train --mode supervised` with the run's TLS fields: the local router is
    TLS-only with mTLS and the role rules, every service holds its role's certificate,
    and the run trains to its budget and is evaluated."""
    certs = pki / "certs"
    run = tmp_path / "run"
    proc = subprocess.run(
        [sys.executable, "-m", "sage", "train", "--mode", "supervised", "--method", "happo_cbf", "--updates", "2",
         "--actors", "1", "--envs-per-actor", "2", "--chunk-len", "8", "--eval-episodes", "1", "--run-dir", str(run),
         "--quiet", "--set", f"transport.tls_root_ca={certs / 'ca.pem'}",
         "--set", f"transport.tls_cert={certs / '{role}.pem'}", "--set", f"transport.tls_key={certs / '{role}.key'}"],
        cwd=ROOT, capture_output=True, text=True, timeout=110)
    assert proc.returncode == 0, proc.stdout + proc.stderr[-3000:]
    assert '"updates": 2' in proc.stdout.strip().splitlines()[-1]
    router_argv = next(e["argv"] for e in map(__import__("json").loads, (run / "supervisor.jsonl").read_text().splitlines())
                       if e.get("event") == "start" and e.get("service") == "router")
    assert "--tls-certs" in router_argv and any(a.startswith("tls/127.0.0.1:") for a in router_argv)


# ------------------------------------------------------------------- one identity per actor id (issue 32, defect 4)
def test_per_actor_certificates_bind_an_actor_to_its_own_id(tmp_path):
    """With per-actor certificates (CN actor-<i>) an actor certificate publishes chunks,
    status and traces only under its own id; the shared actor identity publishes none."""
    certs = tmp_path / "certs"
    dtls.make_test_certs(certs, actors=2)
    port = free_tcp_port()
    endpoint = f"tls/127.0.0.1:{port}"
    proc = subprocess.Popen([sys.executable, "-m", "deploy.router", "--tls-certs", str(certs), "--run-id", RUN,
                             "--listen", endpoint, "--actors", "2"],
                            cwd=ROOT, stderr=subprocess.PIPE, stdout=subprocess.DEVNULL, text=True)
    buses: list[Bus] = []
    try:
        assert "listening" in proc.stderr.readline()
        t = TransportConfig(mode="client", connect=[endpoint], tls_root_ca=str(certs / "ca.pem"),
                            tls_cert=str(certs / "{role}.pem"), tls_key=str(certs / "{role}.key"))
        learner = Bus.from_transport(t, role="learner")
        actor0 = Bus.from_transport(t, role="actor", member=0)   # picks actor-0.pem
        shared = Bus.open(connect=[endpoint], mode="client", role="actor",
                          tls=TlsFiles(str(certs / "ca.pem"), str(certs / "{role}.pem"), str(certs / "{role}.key")))
        buses += [learner, actor0, shared]
        inbox = Inbox()
        learner.subscribe(keys.traj_all(RUN), inbox)
        time.sleep(0.3)
        actor0.publish(keys.traj(RUN, 1), b"as-actor-1")       # forged id: denied by the router
        shared.publish(keys.traj(RUN, 0), b"shared-identity")   # the shared actor cert: denied too
        time.sleep(0.3)
        actor0.publish(keys.traj(RUN, 0), b"own")               # positive control, same path
        wait_for(lambda: inbox.payloads(), 5, "actor 0's own chunk")
        time.sleep(0.3)
        assert inbox.items == [("traj/0", b"own")]
    finally:
        for b in buses:
            b.close()
        proc.terminate()
        try:
            proc.wait(15)
        finally:
            if proc.poll() is None:
                proc.kill()


def test_per_actor_permissions_only_narrow_what_an_actor_publishes():
    perms = dtls.per_actor_permissions(2)
    assert "actor" not in perms and perms["actor-1"]["put"] == ("traj/1", "status/actor/1", "trace/1")
    assert perms["actor-1"]["subscribe"] == dtls.ROLE_PERMISSIONS["actor"]["subscribe"]
    assert perms["actor-1"]["query"] == dtls.ROLE_PERMISSIONS["actor"]["query"]
    acl = dtls.access_control(RUN, actors=2)
    assert {s["id"] for s in acl["subjects"]} == {"learner", "shield", "supervisor", "cli", "actor-0", "actor-1"}
