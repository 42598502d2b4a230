"""A Zenoh router as a plain Python process (no ``zenohd`` binary needed).

    python -m deploy.router                                  # deploy/zenoh-router.json5 (tcp/0.0.0.0:7447)
    python -m deploy.router --listen tcp/127.0.0.1:17447      # override the listen endpoint

Services on this or other hosts list the router in their config
(``transport.connect = ["tcp/<router-host>:7447"]``) and reach each other
through it; see deploy/README.md. ``zenohd -c deploy/zenoh-router.json5``
does the same job where the Zenoh router binary is installed.
"""
from __future__ import annotations

import argparse
import json
import signal
import sys
import threading
from pathlib import Path

DEFAULT_CONFIG = Path(__file__).with_name("zenoh-router.json5")


def router_config(config_path: str | Path = DEFAULT_CONFIG, listen: list[str] | None = None):
    """The router's ``zenoh.Config``: the JSON5 file, with ``mode`` forced to
    ``router`` and the listen endpoints replaced when ``listen`` is given."""
    import zenoh

    path = Path(config_path)
    if not path.is_file():
        raise FileNotFoundError(f"zenoh router config {path} not found")
    cfg = zenoh.Config.from_file(str(path))
    cfg.insert_json5("mode", json.dumps("router"))
    if listen:
        cfg.insert_json5("listen/endpoints", json.dumps(list(listen)))
    return cfg


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m deploy.router", description=__doc__.splitlines()[0])
    p.add_argument("--config", default=str(DEFAULT_CONFIG), help="Zenoh JSON5 config (default: %(default)s)")
    p.add_argument("--listen", action="append", default=None,
                   help="endpoint to listen on, e.g. tcp/0.0.0.0:7447 (repeatable; replaces the file's list)")
    args = p.parse_args(argv)
    import zenoh

    stop = threading.Event()
    for sig in (signal.SIGTERM, signal.SIGINT):
        signal.signal(sig, lambda *_: stop.set())
    session = zenoh.open(router_config(args.config, args.listen))
    endpoints = args.listen or "from " + args.config
    print(f"zenoh router {session.zid()} listening on {endpoints}", file=sys.stderr, flush=True)
    try:
        while not stop.wait(0.5):
            pass
    finally:
        session.close()  # an unclosed session can keep the interpreter from exiting
    return 0


if __name__ == "__main__":
    sys.exit(main())
