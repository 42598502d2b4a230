"""A Zenoh router as a plain Python process (no ``zenohd`` binary needed).

    python -m deploy.router                                  # deploy/zenoh-router.json5 (tcp/127.0.0.1:7447)
    python -m deploy.router --listen tcp/10.0.0.1:7447        # override the listen endpoint
    python -m deploy.router --tls-certs deploy/certs --run-id exp42 --listen tls/10.0.0.1:7447
                                                             # mutual TLS + per-role access control

Services on this or other hosts list the router in their config
(``transport.connect = ["tcp/<router-host>:7447"]``) and reach each other
through it; see deploy/README.md. ``zenohd -c deploy/zenoh-router.json5``
does the same job where the Zenoh router binary is installed. The shipped
config only listens on loopback; exposing the router to a network without
``--tls-certs`` lets anyone who reaches it publish and query any key
(deploy/README.md, "Secure deployment").
"""
from __future__ import annotations

import argparse
import json
import signal
import sys
import threading
from pathlib import Path

DEFAULT_CONFIG = Path(__file__).with_name("zenoh-router.json5")


def router_config(config_path: str | Path = DEFAULT_CONFIG, listen: list[str] | None = None,
                  max_message_bytes: int = 0):
    """The router's ``zenoh.Config``: the JSON5 file, with ``mode`` forced to
    ``router``, the listen endpoints replaced when ``listen`` is given, and
    Zenoh's limit on a received message set when ``max_message_bytes`` > 0."""
    import zenoh

    from common.transport import MAX_MESSAGE_SIZE_KEY

    path = Path(config_path)
    if not path.is_file():
        raise FileNotFoundError(f"zenoh router config {path} not found")
    cfg = zenoh.Config.from_file(str(path))
    cfg.insert_json5("mode", json.dumps("router"))
    if listen:
        cfg.insert_json5("listen/endpoints", json.dumps(list(listen)))
    if max_message_bytes > 0:
        cfg.insert_json5(MAX_MESSAGE_SIZE_KEY, json.dumps(int(max_message_bytes)))
    return cfg


def secure_router_config(certs_dir: str | Path, listen: list[str] | None = None, run_id: str | None = None,
                         max_message_bytes: int = 0, actors: int = 0):
    """The router's ``zenoh.Config`` with mutual TLS and the per-role access
    control of ``deploy/tls.py`` (``certs_dir`` holds ca.pem, router.pem, router.key)."""
    import zenoh

    from deploy.tls import secure_router_config as build

    from common.transport import MAX_MESSAGE_SIZE_KEY

    body = build(certs_dir, run_id=run_id, listen=listen or ["tls/127.0.0.1:7447"], actors=actors)
    cfg = zenoh.Config.from_json5(json.dumps(body))
    if max_message_bytes > 0:
        cfg.insert_json5(MAX_MESSAGE_SIZE_KEY, json.dumps(int(max_message_bytes)))
    return cfg


def _malloc_trim():
    """glibc's ``malloc_trim(0)`` (a no-op elsewhere): Zenoh frees a large message's
    buffers after routing it, but the heap keeps the pages until trimmed."""
    import ctypes

    try:
        fn = ctypes.CDLL("libc.so.6").malloc_trim
    except (OSError, AttributeError):
        return lambda: None
    return lambda: fn(0)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m deploy.router", description=__doc__.splitlines()[0])
    p.add_argument("--config", default=str(DEFAULT_CONFIG), help="Zenoh JSON5 config (default: %(default)s)")
    p.add_argument("--listen", action="append", default=None,
                   help="endpoint to listen on, e.g. tcp/127.0.0.1:7447 or tls/10.0.0.1:7447 "
                        "(repeatable; replaces the file's list)")
    p.add_argument("--tls-certs", default=None, metavar="DIR",
                   help="secure profile instead of --config: TLS-only, client certificates required, "
                        "per-role access control (certificates from `python -m deploy.tls certs`)")
    p.add_argument("--run-id", default=None, help="with --tls-certs: allow only keys of sage/<run-id>/ (default: any run)")
    p.add_argument("--actors", type=int, default=0,
                   help="with --tls-certs: one identity per actor id (certificates actor-<i>.pem from "
                        "`python -m deploy.tls certs --actors N`): each actor publishes only as itself")
    p.add_argument("--max-message-bytes", type=int, default=0,
                   help="largest message a link may carry (Zenoh's transport/link/rx/max_message_size; "
                        "0: Zenoh's default, 1 GiB); `sage up` passes its run's bound")
    args = p.parse_args(argv)
    import zenoh

    if args.run_id and not args.tls_certs:
        p.error("--run-id needs --tls-certs")
    stop = threading.Event()
    for sig in (signal.SIGTERM, signal.SIGINT):
        signal.signal(sig, lambda *_: stop.set())
    if args.tls_certs:
        cfg = secure_router_config(args.tls_certs, args.listen, args.run_id, args.max_message_bytes, args.actors)
    else:
        cfg = router_config(args.config, args.listen, args.max_message_bytes)
    session = zenoh.open(cfg)
    endpoints = args.listen or ("tls/127.0.0.1:7447 (mTLS + access control)" if args.tls_certs
                                else "from " + args.config)
    print(f"zenoh router {session.zid()} listening on {endpoints}", file=sys.stderr, flush=True)
    trim = _malloc_trim()
    try:
        while not stop.wait(5.0):
            trim()   # hand the heap that large messages' buffers left behind back to the OS
    finally:
        session.close()  # an unclosed session can keep the interpreter from exiting
    return 0


if __name__ == "__main__":
    sys.exit(main())
