"""A SAGE run as supervised processes: the local Zenoh router (unless the
config names one), then the members of ``services.launcher.run_members``, each
its documented entry point (``services.launcher.entry_argv``), under
``deploy.supervisor.Supervisor``. The status line is the services' heartbeats
(``common.status.StatusBoard``); when the learner reaches its budget a
``control`` stop goes to every service of the run, remote actors included.

    sage up --actors 3 --updates 50                      # fresh run, local router
    sage up --config runs/<id>/config.json               # a saved run config
    sage train --mode supervised ...                     # the same, from sage train
    sage up --config RUN.json --roles actor --actor-ids 4-7 --connect tcp/HOST:7447   # actors on another host
"""
from __future__ import annotations

import os
import sys
from pathlib import Path
from typing import Sequence

from common.rundir import RunDir
from common.status import StatusBoard
from common.transport import TlsFiles
from deploy.driver import RunDriver, free_tcp_port
from deploy.supervisor import ServiceSpec, Supervisor, SupervisorConfig
from services.config import TrainConfig
from services.launcher import ROLES, entry_argv, run_members

# Prometheus port convention (deploy/prometheus.yml): base+0 learner, base+1+k shield shard k, base+10+i actor i
METRICS_OFFSETS = {"learner": 0, "shield": 1, "actor_base": 10}


def default_actor_count() -> int:
    """One actor per core, leaving one core for the learner and shield (at least 1)."""
    try:
        cores = len(os.sched_getaffinity(0))
    except AttributeError:
        cores = os.cpu_count() or 1
    return max(1, cores - 1)


def parse_ids(text: str) -> list[int]:
    """``"0-3,7"`` -> ``[0, 1, 2, 3, 7]``."""
    out: list[int] = []
    for part in filter(None, (p.strip() for p in text.split(","))):
        lo, _, hi = part.partition("-")
        if not lo.isdigit() or (hi and not hi.isdigit()):
            raise ValueError(f"bad id range {part!r} (expected e.g. 0-3,7)")
        out += list(range(int(lo), int(hi or lo) + 1))
    if not out or len(set(out)) != len(out):
        raise ValueError(f"bad id list {text!r}: empty or repeated ids")
    return out


def service_specs(config_path: str | Path, roles: Sequence[str] = ROLES, actor_ids: Sequence[int] = (0,),
                  python: str = sys.executable, shields: int = 1) -> list[ServiceSpec]:
    """The run's members as supervised services (``shields`` shield shards); the
    learner's exit 0 ends the run (it checkpoints on SIGTERM, so it is stopped
    in the first wave)."""
    return [ServiceSpec(m.name, entry_argv(m, config_path, python), ends_run=m.role == "learner")
            for m in run_members(actor_ids, roles, shields)]


def router_spec(port: int, python: str = sys.executable, host: str = "127.0.0.1",
                tls_certs: str | None = None, run_id: str | None = None, max_message_bytes: int = 0,
                actors: int = 0) -> ServiceSpec:
    """The local router; with ``tls_certs`` (a ``python -m deploy.tls certs`` folder)
    TLS-only with client certificates and the per-role access rules of ``run_id``
    (per actor id too when ``actors`` > 0 and the folder holds ``actor-<i>.pem``);
    ``max_message_bytes`` > 0: the largest message its links carry (the run's bound)."""
    if tls_certs:
        argv = [python, "-m", "deploy.router", "--listen", f"tls/{host}:{port}", "--tls-certs", str(tls_certs),
                "--run-id", str(run_id)]
        if actors > 0 and (Path(tls_certs) / "actor-0.pem").is_file():
            argv += ["--actors", str(int(actors))]
    else:
        argv = [python, "-m", "deploy.router", "--listen", f"tcp/{host}:{port}"]
    if max_message_bytes > 0:
        argv += ["--max-message-bytes", str(int(max_message_bytes))]
    return ServiceSpec("router", argv, stop_wave=1, ready_tcp=(host, port))


def prepare_run(config_path: str | Path, *, actors: int | None = None, roles: Sequence[str] = ROLES,
                actor_ids: Sequence[int] | None = None, python: str = sys.executable, absolute: bool = False,
                who: str = "supervisor", out=None) -> tuple[TrainConfig, list[ServiceSpec], Path]:
    """Every placement's preparation of a run: the child config the services read
    (``<run_dir>/supervised_config.json``: one process per service, an actor cut
    off from the shield exits to be restarted) and the service specs, the local
    router first when the config names none (a free 127.0.0.1 port, every member
    a client of it). ``absolute``: the run directory and the certificates as
    absolute paths, so the config means the same on every node (Ray)."""
    cfg = TrainConfig.load(config_path)
    if actors is not None:
        cfg.actors = int(actors)
    cfg.mode = "supervised"
    cfg.actor.exit_on_unhealthy = True  # an actor cut off from the shield exits; the placement restarts it
    if absolute:
        cfg.run_dir = str(Path(cfg.run_dir).resolve())
    cfg.validate()
    ids = list(actor_ids) if actor_ids is not None else list(range(cfg.actors))
    run = RunDir(cfg.run_dir)
    specs: list[ServiceSpec] = []
    tls = TlsFiles.from_transport(cfg.transport)
    if not cfg.transport.connect:
        port = free_tcp_port()   # free on the driver's node, where the router is placed
        # with TLS configured the local router uses the folder of the run's CA (certs/ca.pem)
        ca = Path(tls.root_ca) if tls is not None else None
        if ca is not None and absolute:
            ca = ca.resolve()
        specs.append(router_spec(port, python, tls_certs=str(ca.parent) if ca else None, run_id=cfg.run_id,
                                 max_message_bytes=cfg.message_bytes_bound(), actors=cfg.actors))
        cfg.transport.connect = [f"{'tls' if tls is not None else 'tcp'}/127.0.0.1:{port}"]
        # client mode: everything goes through the router. Peers with gossip
        # off (common/transport.py) attached to one router do not hear each other.
        cfg.transport.mode = "client"
    elif cfg.transport.mode != "client":
        print(f"{who}: warning: transport.mode is {cfg.transport.mode!r}; services attached to a router "
              "should use \"client\" (deploy/README.md)", file=out or sys.stderr)
    child_config = cfg.save(run.supervised_config)
    specs += service_specs(child_config, roles, ids, python, shields=cfg.shields)
    return cfg, specs, child_config


def run_with_status(driver: RunDriver, cfg: TrainConfig, install_signals: bool = True) -> int:
    """``driver.run`` with the services' heartbeats as its status line; when the
    learner reaches its budget a ``control`` stop goes to every service of the
    run, wherever it is (remote actors included)."""
    tls = TlsFiles.from_transport(cfg.transport)
    board = StatusBoard(cfg.run_id, stale_after_s=max(5.0, 5 * cfg.status_period_s))

    def open_status():
        return board.subscribe(cfg.transport.connect, tls=tls)

    def on_finish(status):
        if status is not None:
            status.stop_run()

    return driver.run(open_status, on_finish, install_signals=install_signals)


def run_supervised(config_path: str | Path, *, actors: int | None = None, roles: Sequence[str] = ROLES,
                   actor_ids: Sequence[int] | None = None, supervisor: SupervisorConfig | None = None,
                   install_signals: bool = True, out=None) -> int:
    """Run the services of the run config at ``config_path`` as supervised
    processes until the learner's budget is reached, a signal arrives, or a
    service exhausts its restart budget. Returns the exit code (0 = finished).

    ``actors`` overrides the config's actor count (the learner waits for one
    chunk per actor per update). Without ``transport.connect`` in the config a
    local router is started on a free 127.0.0.1 port. The config the children
    read is written to ``<run_dir>/supervised_config.json``.
    """
    cfg, specs, _ = prepare_run(config_path, actors=actors, roles=roles, actor_ids=actor_ids, out=out)
    sup = Supervisor(specs, cfg.run_dir, supervisor, out=out)
    print(f"supervisor: run {cfg.run_id}, {len(specs)} processes ({', '.join(s.name for s in specs)}), "
          f"router {cfg.transport.connect[0]}, run dir {sup.paths.root}", file=sup.out, flush=True)
    return run_with_status(sup, cfg, install_signals)
