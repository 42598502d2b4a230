"""Secure deployment profile: test certificates, and a router config with
mutual TLS and per-role access control (deploy/README.md, "Secure deployment").

    python -m deploy.tls certs --out deploy/certs                  # CA + router + one cert per role
    python -m deploy.tls router-config --certs deploy/certs --run-id exp42 \\
        --listen tls/127.0.0.1:7447 --out deploy/certs/router-exp42.json5
    python -m deploy.router --config deploy/certs/router-exp42.json5

Identity is the certificate: every role has one certificate whose subject
common name is the role name (``learner``, ``actor``, ``shield``,
``supervisor``, ``cli``), signed by the run's CA. The router only accepts TLS
links whose client certificate chains to that CA (``enable_mtls``), and its
``access_control`` section matches each link by ``cert_common_names`` and
allows exactly the traffic of ``ROLE_PERMISSIONS``; everything else is denied
(``default_permission: "deny"``). Access control is enforced by the router, so
services must reach each other *through* it: ``transport.mode = "client"``.

Certificates are made with the ``openssl`` command line tool (no Python
dependency). They are test/lab certificates: a real deployment keeps the CA
key offline and issues the role certificates from its own PKI; the router
config only needs the CA certificate and the router's own pair.
"""
from __future__ import annotations

import argparse
import json
import os
import secrets
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path
from typing import Iterable, Mapping, Sequence

from common.keys import PREFIX, check_id

# What each role may do, as key expressions relative to sage/<run_id>/.
#   put       the role publishes there            (ingress put)
#   subscribe the role declares a subscriber and receives the samples
#                                                  (ingress declare_subscriber, egress put)
#   query     the role sends gets and receives the replies
#                                                  (ingress query, egress reply)
#   serve     the role declares a queryable, is sent the queries and replies
#                                                  (ingress declare_queryable + reply, egress query)
# Matches the services: every service publishes its own status/<role>/<id>
# and listens to control (services/base.py); learner -> params, traj/* ->
# learner; actors query the shield; the supervisor (and the `cli` operator
# identity) read status/** and may publish a control stop.
ROLE_PERMISSIONS: dict[str, dict[str, tuple[str, ...]]] = {
    "learner": {"put": ("params", "status/learner/*"), "subscribe": ("traj/*", "control")},
    # actors read the learner's heartbeat: parameter versions are fenced by it (services/actor)
    "actor": {"put": ("traj/*", "status/actor/*", "trace/*"), "subscribe": ("params", "control", "status/learner/*"),
              "query": ("shield/*",)},
    "shield": {"put": ("status/shield/*",), "subscribe": ("control",), "serve": ("shield/*",)},
    "supervisor": {"put": ("control", "status/supervisor/*"), "subscribe": ("status/**",)},
    "cli": {"put": ("control",), "subscribe": ("status/**", "trace/*")},
}
ROLES = tuple(ROLE_PERMISSIONS)


def actor_cn(actor_id: int) -> str:
    """The common name of actor ``actor_id``'s own certificate: with per-actor
    certificates (``actors`` > 0 below) an actor may publish only under its own
    id (traj/<id>, status/actor/<id>, trace/<id>), so it cannot send chunks as another."""
    return f"actor-{int(actor_id)}"


def per_actor_permissions(actors: int, permissions: Mapping[str, Mapping[str, Sequence[str]]] = ROLE_PERMISSIONS
                          ) -> dict[str, dict[str, tuple[str, ...]]]:
    """``permissions`` with the shared ``actor`` identity replaced by one per actor id:
    each may read what an actor reads but publish only its own keys."""
    out = {role: dict(perms) for role, perms in permissions.items() if role != "actor"}
    base = permissions["actor"]
    for i in range(int(actors)):
        own = tuple(k.replace("*", str(i)) if k.startswith(("traj/", "status/actor/", "trace/")) else k
                    for k in base.get("put", ()))
        out[actor_cn(i)] = {**base, "put": own}
    return out

# (messages, flow) at the router for each kind of permission. Ingress = from
# the role's link into the router, egress = from the router to the role.
# Nothing else is needed in Zenoh 1.10 client mode (checked: with egress
# declare_subscriber / declare_queryable also allowed, nothing changes).
_GRANTS: dict[str, tuple[tuple[tuple[str, ...], str], ...]] = {
    "put": ((("put",), "ingress"),),
    "subscribe": ((("declare_subscriber",), "ingress"), (("put",), "egress")),
    "query": ((("query",), "ingress"), (("reply",), "egress")),
    "serve": ((("declare_queryable", "reply"), "ingress"), (("query",), "egress")),
}


# --------------------------------------------------------------- certificates
def _openssl() -> str:
    exe = shutil.which("openssl")
    if exe is None:
        raise RuntimeError("the openssl command line tool is needed to make certificates (apt-get install openssl)")
    return exe


def _run(args: Sequence[str]) -> None:
    r = subprocess.run(list(args), capture_output=True, text=True)
    if r.returncode != 0:
        raise RuntimeError(f"{' '.join(args)} failed ({r.returncode}): {r.stderr.strip()}")


def _new_key(path: Path) -> None:
    _run([_openssl(), "genpkey", "-algorithm", "EC", "-pkeyopt", "ec_paramgen_curve:P-256", "-out", str(path)])
    os.chmod(path, 0o600)


def make_ca(out_dir: str | Path, name: str = "ca", cn: str = "sage-ca", days: int = 365) -> tuple[Path, Path]:
    """A self-signed CA: ``<name>.pem`` and ``<name>.key`` in ``out_dir``."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    key, crt = out / f"{name}.key", out / f"{name}.pem"
    _new_key(key)
    _run([_openssl(), "req", "-x509", "-new", "-key", str(key), "-out", str(crt), "-days", str(days),
          "-subj", f"/CN={cn}", "-addext", "basicConstraints=critical,CA:TRUE",
          "-addext", "keyUsage=critical,keyCertSign,cRLSign"])
    return crt, key


def make_cert(out_dir: str | Path, cn: str, ca: tuple[Path, Path], *, name: str | None = None,
              hosts: Iterable[str] = (), days: int = 365) -> tuple[Path, Path]:
    """A certificate with subject ``CN=cn`` signed by ``ca`` (cert, key); usable
    as TLS server and client certificate. ``hosts`` (IPs or DNS names) go into
    subjectAltName, which is what a client checks the router's name against."""
    out = Path(out_dir)
    name = name or cn
    key, crt = out / f"{name}.key", out / f"{name}.pem"
    _new_key(key)
    sans = [f"DNS:{cn}"] + [("IP:" if _is_ip(h) else "DNS:") + h for h in hosts]
    ext = ("basicConstraints=critical,CA:FALSE\nkeyUsage=critical,digitalSignature\n"
           "extendedKeyUsage=serverAuth,clientAuth\n" f"subjectAltName={','.join(sans)}\n")
    with tempfile.TemporaryDirectory() as tmp:
        csr, extfile = Path(tmp) / "req.csr", Path(tmp) / "ext.cnf"
        extfile.write_text(ext)
        _run([_openssl(), "req", "-new", "-key", str(key), "-out", str(csr), "-subj", f"/CN={cn}"])
        _run([_openssl(), "x509", "-req", "-in", str(csr), "-CA", str(ca[0]), "-CAkey", str(ca[1]),
              "-set_serial", "0x" + secrets.token_hex(16), "-days", str(days), "-out", str(crt),
              "-extfile", str(extfile)])
    return crt, key


def _is_ip(h: str) -> bool:
    import ipaddress

    try:
        ipaddress.ip_address(h)
        return True
    except ValueError:
        return False


def make_test_certs(out_dir: str | Path, roles: Iterable[str] = ROLES,
                    router_hosts: Iterable[str] = ("127.0.0.1", "localhost"), days: int = 365,
                    actors: int = 0) -> dict[str, Path]:
    """CA (``ca.pem``/``ca.key``), the router's pair (``router.pem``/``.key``,
    subjectAltName = ``router_hosts``) and ``<role>.pem``/``<role>.key`` with
    CN = role for every role; with ``actors`` > 0 also ``actor-<i>.pem``/``.key``
    (CN = ``actor_cn(i)``) for each actor id. Returns {name: path}."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    # private keys must never end up in a commit (e.g. --out deploy/certs)
    (out / ".gitignore").write_text("# generated by python -m deploy.tls certs: private keys\n*\n")
    ca = make_ca(out)
    files = {"ca": ca[0], "ca_key": ca[1]}
    files["router"], files["router_key"] = make_cert(out, "router", ca, hosts=router_hosts, days=days)
    for role in [*roles, *(actor_cn(i) for i in range(int(actors)))]:
        check_id(role, "role")
        files[role], files[f"{role}_key"] = make_cert(out, role, ca, days=days)
    return files


# --------------------------------------------------------------- router config
def access_control(run_id: str | None = None,
                   permissions: Mapping[str, Mapping[str, Sequence[str]]] = ROLE_PERMISSIONS,
                   actors: int = 0) -> dict:
    """Zenoh 1.x ``access_control`` section: default deny, and for every role
    one subject (``cert_common_names: [role]``), its rules and one policy.
    ``run_id=None`` writes ``sage/*/...`` (any run on this router). ``actors`` > 0:
    one identity per actor id instead of the shared one (``per_actor_permissions``)."""
    if actors > 0:
        permissions = per_actor_permissions(actors, permissions)
    root = f"{PREFIX}/{check_id(run_id, 'run id') if run_id else '*'}"
    rules, subjects, policies = [], [], []
    for role, perms in permissions.items():
        rule_ids = []
        for kind, rel_keys in perms.items():
            if kind not in _GRANTS:
                raise ValueError(f"{role}: unknown permission {kind!r} (one of {sorted(_GRANTS)})")
            if not rel_keys:
                continue
            for i, (messages, flow) in enumerate(_GRANTS[kind]):
                rid = f"{role}-{kind}-{i}"
                rules.append({"id": rid, "permission": "allow", "flows": [flow], "messages": list(messages),
                              "key_exprs": [f"{root}/{k}" for k in rel_keys]})
                rule_ids.append(rid)
        subjects.append({"id": role, "cert_common_names": [role]})
        policies.append({"id": f"{role}-policy", "rules": rule_ids, "subjects": [role]})
    return {"enabled": True, "default_permission": "deny", "rules": rules, "subjects": subjects,
            "policies": policies}


def router_tls(certs: str | Path, *, cert: str = "router.pem", key: str = "router.key", ca: str = "ca.pem") -> dict:
    """``transport/link/tls`` of the router: its own pair, the CA that client
    certificates must chain to, and mTLS on."""
    d = Path(certs).resolve()
    return {"root_ca_certificate": str(d / ca), "listen_certificate": str(d / cert),
            "listen_private_key": str(d / key), "enable_mtls": True,
            # the router connects to nothing by default; a bridged router uses its own pair
            "connect_certificate": str(d / cert), "connect_private_key": str(d / key),
            "verify_name_on_connect": True,
            "close_link_on_expiration": True}   # a link ends when the certificate behind it expires


def secure_router_config(certs: str | Path, *, run_id: str | None = None,
                         listen: Sequence[str] = ("tls/127.0.0.1:7447",),
                         permissions: Mapping[str, Mapping[str, Sequence[str]]] = ROLE_PERMISSIONS,
                         actors: int = 0) -> dict:
    """The whole router config (a dict; JSON is valid JSON5): TLS-only listen
    endpoints, mTLS, access control, no scouting."""
    listen = [listen] if isinstance(listen, str) else list(listen)
    for ep in listen:
        if not ep.startswith("tls/"):
            raise ValueError(f"secure router listens on tls/ endpoints only, got {ep!r}")
    return {
        "mode": "router",
        "listen": {"endpoints": listen},
        "connect": {"endpoints": []},
        # no discovery at all: gossip would advertise locators that bypass the router's ACL
        "scouting": {"multicast": {"enabled": False}, "gossip": {"enabled": False}},
        "transport": {"link": {"tls": router_tls(certs)}},
        "access_control": access_control(run_id, permissions, actors),
    }


def write_router_config(path: str | Path, certs: str | Path, **kw) -> Path:
    p = Path(path)
    p.parent.mkdir(parents=True, exist_ok=True)
    body = json.dumps(secure_router_config(certs, **kw), indent=2)
    p.write_text("// generated by `python -m deploy.tls router-config` (Zenoh 1.x): mTLS + access control\n"
                 + body + "\n")
    return p


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m deploy.tls", description=__doc__.splitlines()[0])
    sub = p.add_subparsers(dest="cmd", required=True)
    c = sub.add_parser("certs", help="make a test CA, the router's certificate and one certificate per role")
    c.add_argument("--out", required=True, help="directory for the PEM files")
    c.add_argument("--roles", default=",".join(ROLES), help="comma-separated roles (CN = role; default %(default)s)")
    c.add_argument("--router-host", action="append", default=None,
                   help="IP or DNS name services use to reach the router (repeatable; default 127.0.0.1, localhost)")
    c.add_argument("--days", type=int, default=365)
    c.add_argument("--actors", type=int, default=0,
                   help="also one certificate per actor id (CN actor-<i>): each actor may publish only as itself")
    r = sub.add_parser("router-config", help="write a router JSON5 with TLS, mTLS and per-role access control")
    r.add_argument("--certs", required=True, help="directory with ca.pem, router.pem, router.key")
    r.add_argument("--out", required=True, help="JSON5 file to write")
    r.add_argument("--run-id", default=None, help="restrict the rules to sage/<run-id>/ (default: any run)")
    r.add_argument("--listen", action="append", default=None, help="tls/ endpoint (default tls/127.0.0.1:7447)")
    r.add_argument("--actors", type=int, default=0, help="per-actor identities actor-0 .. actor-<N-1> (see certs)")
    args = p.parse_args(argv)
    if args.cmd == "certs":
        files = make_test_certs(args.out, [x for x in args.roles.split(",") if x],
                                args.router_host or ("127.0.0.1", "localhost"), args.days, args.actors)
        print(f"wrote {len(files)} files to {args.out}: " + ", ".join(sorted(p.name for p in files.values())))
    else:
        out = write_router_config(args.out, args.certs, run_id=args.run_id,
                                  listen=args.listen or ["tls/127.0.0.1:7447"], actors=args.actors)
        print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
