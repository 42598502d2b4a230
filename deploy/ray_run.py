"""A SAGE run placed on a Ray cluster: Ray only places and restarts the
processes; the services talk over Zenoh + msgpack exactly as under the local
supervisor (``deploy/supervised_run.py``).

    sage up --ray auto --actors 8 --updates 500        # a running cluster (`ray start --head`)
    sage train --mode ray --ray 10.0.0.1:6379 ...      # the same, from sage train
    sage train --mode ray --ray local                  # a one-machine Ray instance of this process

Every service -- the router, each shield shard, the learner, each actor -- is
one Ray actor (``ServiceRunner``) with its declared resources (``RayPlacement``:
1 CPU per actor, shield and learner, none for the router). Creating the Ray
actor starts the service's documented entry point, the same command line the
local supervisor runs (``service_specs`` / ``router_spec``), as a child process
of the Ray worker. When that process exits non-zero the Ray actor exits with
it, so Ray's restart policy (``max_restarts``) re-creates the actor, which
starts the command again; a restarted learner resumes from its newest
checkpoint, as it does under the supervisor. The learner's exit 0 (update or
time budget reached) ends the run: a ``control`` stop goes to every service,
then each process gets SIGTERM and, after ``term_deadline_s``, SIGKILL; the Ray
actors are killed last. Ctrl-C (SIGINT) or SIGTERM does the same; exit code
128 + signal.

Where things run and what they need (deploy/README.md, "Ray cluster"):

* the driver (this process) must run on a node of the cluster; the router,
  the learner and the log sink are pinned to that node, so the run directory
  (config, checkpoints, metrics, logs, ``supervisor.jsonl``, ``status.json``)
  is the driver's, as with ``sage up``; actors are spread over the nodes;
* each service's stdout/stderr is shipped back through Ray to
  ``<run_dir>/logs/<service>.log`` on the driver's node (``LogSink``), and the
  config file the children read is copied to the same path on every node that
  lacks it, so no shared filesystem is needed;
* every node has the same Python environment at the same path (Ray needs that
  anyway);
* without ``transport.connect`` the local router listens on 127.0.0.1 of the
  driver's node, which only services on that host reach: a cluster of several
  hosts needs a router every node can reach (``--connect``), else the run is
  refused before anything starts.

Ray is imported only when a function here is called: nothing else needs it.
"""
from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Sequence

from common.rundir import atomic_write_text
from deploy.driver import EXIT_GAVE_UP, Member, RunDriver, kill_group, parent_death_argv
from deploy.supervised_run import prepare_run, run_with_status
from deploy.supervisor import ServiceSpec
from services.config import TrainConfig
from services.launcher import ROLES, run_members

INSTALL_HINT = "pip install -e '.[cluster]'"
# the resource names that Ray takes as num_cpus / num_gpus, never in `resources`
_BUILTIN_RESOURCES = {"CPU": "num_cpus", "GPU": "num_gpus"}


class ClusterError(ValueError):
    """The cluster cannot take the run (no Ray, bad address, missing resources):
    a one-line reason, before anything is started."""


@dataclass
class RayPlacement:
    """How the run's services are placed and restarted on the cluster."""
    address: str = "auto"              # "auto" (a running cluster), "HOST:PORT", or "local" (a fresh instance)
    cpus: dict[str, float] = field(default_factory=lambda: {"router": 0.0, "shield": 1.0, "learner": 1.0,
                                                            "actor": 1.0})
    # extra Ray resources by service name ("actor-1") or role ("actor"), e.g. a custom
    # resource that only some nodes have pins those services there
    resources: dict[str, dict[str, float]] = field(default_factory=dict)
    max_restarts: int = 5              # per service, over the whole run (Ray's restart policy)
    restart_delay_s: float = 0.5       # a re-created service waits this long before it starts again
    term_deadline_s: float = 15.0      # SIGTERM, wait this long, then SIGKILL
    placement_timeout_s: float = 120.0  # a service the cluster cannot place by then ends the run
    ready_timeout_s: float = 30.0      # the local router must accept TCP connections by then
    poll_s: float = 0.1
    status_period_s: float = 1.0       # live line and status.json refresh
    status_log_period_s: float = 10.0  # when stderr is not a terminal: one status line this often

    def request(self, name: str) -> dict:
        """The Ray actor options of service ``name``: ``num_cpus`` of its role, plus
        its extra resources (role first, then the service's own)."""
        role = role_of(name)
        extra = {**self.resources.get(role, {}), **self.resources.get(name, {})}
        opts: dict = {"num_cpus": float(self.cpus.get(role, 1.0)), "resources": {}}
        for key, amount in extra.items():
            if key in _BUILTIN_RESOURCES:
                opts[_BUILTIN_RESOURCES[key]] = float(amount)
            else:
                opts["resources"][key] = float(amount)
        return opts


def role_of(name: str) -> str:
    """``actor-3`` -> ``actor``, ``shield-1`` -> ``shield``, ``learner``, ``router``."""
    return name.split("-", 1)[0]


def parse_resources(items: Sequence[str]) -> dict[str, dict[str, float]]:
    """``["actor-1=node_b:1", "learner=GPU:1,big_mem:1"]`` -> ``{"actor-1": {"node_b": 1.0}, ...}``;
    a ``ValueError`` naming a bad item."""
    out: dict[str, dict[str, float]] = {}
    for item in items:
        name, sep, rest = item.partition("=")
        if not sep or not name.strip() or not rest.strip():
            raise ValueError(f"--ray-resources {item!r}: expected SERVICE=RESOURCE:AMOUNT[,RESOURCE:AMOUNT]")
        res = out.setdefault(name.strip(), {})
        for part in filter(None, (p.strip() for p in rest.split(","))):
            key, sep, amount = part.partition(":")
            try:
                value = float(amount) if sep else 1.0
            except ValueError:
                raise ValueError(f"--ray-resources {item!r}: {amount!r} is not a number") from None
            if not key or not value > 0 or value == float("inf"):
                raise ValueError(f"--ray-resources {item!r}: need RESOURCE:AMOUNT with an amount > 0")
            res[key] = value
    return out


# ----------------------------------------------------------------- connecting
def import_ray():
    """The ``ray`` module, or a ``ClusterError`` saying how to install it."""
    try:
        import ray
    except ImportError:
        raise ClusterError(f"Ray is not installed; it is the optional extra 'cluster': {INSTALL_HINT}") from None
    return ray


def connect(address: str, local_cpus: int | None = None):
    """Join the Ray cluster at ``address`` (``auto``, ``HOST:PORT`` or ``local``) as
    its driver, once per process; the ``ray`` module. ``local`` starts a fresh
    one-machine instance with ``local_cpus`` logical CPUs (default: the cores). A
    ``ClusterError`` with one line when Ray is missing or nothing answers there."""
    # the address's form first: a malformed one is refused the same with or without Ray
    address = address.strip()
    if address.startswith("ray://"):
        raise ClusterError(f"--ray {address}: Ray Client addresses are not supported; run sage on a node of "
                           "the cluster (the driver's node holds the run directory) and give the GCS address")
    if address not in ("auto", "local"):
        host, sep, port = address.rpartition(":")
        if not sep or not host or not port.isdigit():
            raise ClusterError(f"--ray {address!r}: expected auto, local or HOST:PORT (the head's GCS address)")
    ray = import_ray()
    if ray.is_initialized():
        return ray
    if address not in ("auto", "local"):
        # ray.init() waits minutes for a GCS that is not there: fail fast instead
        try:
            with socket.create_connection((host, int(port)), timeout=5.0):
                pass
        except OSError as exc:
            raise ClusterError(f"--ray {address}: no Ray cluster answers there ({exc.strerror or exc})") from None
    import logging

    try:
        # services log into their own files (LogSink); Ray's worker logs stay on the nodes
        extra = {"num_cpus": local_cpus} if address == "local" and local_cpus else {}
        ray.init(address=address, log_to_driver=False, logging_level=logging.WARNING, **extra)
    except ConnectionError as exc:
        hint = " (start one with `ray start --head`, or use --ray local)" if address == "auto" else ""
        raise ClusterError(f"--ray {address}: {str(exc).splitlines()[0]}{hint}") from None
    return ray


def service_names(cfg: TrainConfig, roles: Sequence[str] = ROLES, actor_ids: Sequence[int] | None = None
                  ) -> list[str]:
    """The services a run of ``cfg`` places: the local router unless the config names one, then its members."""
    ids = list(actor_ids) if actor_ids is not None else list(range(cfg.actors))
    return ([] if cfg.transport.connect else ["router"]) + [m.name for m in run_members(ids, roles, cfg.shields)]


def cpus_for_local(placement: RayPlacement, names: Sequence[str]) -> int:
    """Logical CPUs for a ``--ray local`` instance: the cores, or what the services ask for if more."""
    asked = sum(placement.request(n)["num_cpus"] for n in names)
    return max(os.cpu_count() or 1, int(asked + 0.999))


def cluster_summary(ray) -> dict:
    """Alive nodes, their addresses and the cluster's total resources."""
    nodes = [n for n in ray.nodes() if n.get("Alive")]
    return {"nodes": len(nodes), "hosts": sorted({n["NodeManagerAddress"] for n in nodes}),
            "resources": {k: v for k, v in ray.cluster_resources().items() if not k.startswith("node:")}}


def check_cluster(ray, placement: RayPlacement, names: Sequence[str]) -> dict:
    """The cluster's summary, or a ``ClusterError`` when it cannot take the services
    ``names``: a local router (127.0.0.1) on a cluster of several hosts, or fewer
    resources than the services ask for in all."""
    cluster = cluster_summary(ray)
    if "router" in names and len(cluster["hosts"]) > 1:
        raise ClusterError(f"the cluster spans {len(cluster['hosts'])} hosts ({', '.join(cluster['hosts'])}) but the "
                           "run's router would listen on 127.0.0.1 of this one; start a router every node can reach "
                           "and give it with --connect (deploy/README.md, \"Ray cluster\")")
    check_capacity({n: placement.request(n) for n in names}, cluster["resources"])
    return cluster


def check_capacity(requests: dict[str, dict], total: dict[str, float]) -> None:
    """A ``ClusterError`` when the cluster as a whole lacks what the services ask for
    (Ray would leave them pending forever)."""
    need: dict[str, float] = {}
    for opts in requests.values():
        need["CPU"] = need.get("CPU", 0.0) + opts.get("num_cpus", 0.0)
        need["GPU"] = need.get("GPU", 0.0) + opts.get("num_gpus", 0.0)
        for key, amount in opts.get("resources", {}).items():
            need[key] = need.get(key, 0.0) + amount
    short = [f"{key} {amount:g} (cluster has {total.get(key, 0.0):g})" for key, amount in sorted(need.items())
             if amount > total.get(key, 0.0) + 1e-9]
    if short:
        raise ClusterError(f"the run's {len(requests)} services need more than the cluster has: {', '.join(short)}; "
                           "add nodes, run fewer actors, or change --ray-resources")


# ----------------------------------------------------------------- inside Ray
def run_logged(argv: Sequence[str], log_path: str | Path, env: dict | None = None) -> int:
    """Run ``argv`` in a Ray task, its output appended to ``log_path`` (on the task's
    node); the exit code. The process dies with the task (cancelled, worker lost)."""
    Path(log_path).parent.mkdir(parents=True, exist_ok=True)
    with open(log_path, "ab") as log:
        proc = subprocess.Popen(parent_death_argv(argv), stdin=subprocess.DEVNULL, stdout=log, stderr=subprocess.STDOUT,
                                start_new_session=True, env=env)
    try:
        return proc.wait()
    finally:
        kill_group(proc.pid, signal.SIGKILL)   # anything it left behind in its group (or a cancelled task)


def _materialize(path: str, text: str) -> None:
    """``text`` at ``path`` on this node unless it is already there (the driver's node,
    a shared filesystem)."""
    p = Path(path)
    try:
        if p.read_text() == text:
            return
    except OSError:
        pass
    atomic_write_text(p, text)


class LogSink:
    """A Ray actor on the driver's node: appends the services' output to
    ``<run_dir>/logs/<service>.log`` and keeps each service's last exit (pid, code)."""

    def __init__(self, log_dir: str):
        self.log_dir = Path(log_dir)
        self.log_dir.mkdir(parents=True, exist_ok=True)
        self.files: dict[str, object] = {}
        self.exits: dict[str, tuple[int, int]] = {}

    def write(self, name: str, data: bytes) -> None:
        f = self.files.get(name)
        if f is None:
            f = self.files[name] = open(self.log_dir / f"{name}.log", "ab")
        f.write(data)
        f.flush()

    def exited(self, name: str, pid: int, code: int, restarting: bool) -> None:
        self.exits[name] = (pid, code)
        then = "Ray restarts it" if restarting else "not restarted"
        self.write(name, f"ray: {name} (pid {pid}) exited with code {code}; {then}\n".encode())

    def last_exit(self, name: str) -> tuple[int, int] | None:
        return self.exits.get(name)

    def close(self) -> None:
        for f in self.files.values():
            f.close()
        self.files.clear()


class ServiceRunner:
    """A Ray actor that is one service: creating it starts the service's command
    (its own process group, output shipped to the ``LogSink``); ``wait`` returns
    the exit code, and a non-zero exit that no ``stop`` asked for ends the Ray
    actor's process too, so Ray re-creates the actor (``max_restarts``) and with
    it the service."""

    def __init__(self, name: str, argv: list[str], *, files: dict[str, str], cwd: str, env: dict[str, str],
                 sink: str, restart_delay_s: float):
        import ray

        ctx = ray.get_runtime_context()
        # the sink by name, not a handle argument: a re-created actor must not depend on
        # constructor arguments kept in the object store
        self.name, self.sink = name, ray.get_actor(sink)
        self.restarted = bool(ctx.was_current_actor_reconstructed)
        self.node = ctx.get_node_id()
        self.host = ray.util.get_node_ip_address()
        self.stopping = False
        if self.restarted:
            time.sleep(restart_delay_s)   # no tight loop of a service that dies at start
        for path, text in files.items():
            _materialize(path, text)
        self.proc = subprocess.Popen(parent_death_argv(argv), stdin=subprocess.DEVNULL, stdout=subprocess.PIPE,
                                     stderr=subprocess.STDOUT, start_new_session=True,
                                     cwd=cwd if os.path.isdir(cwd) else None, env={**os.environ, **env})
        what = "restarted" if self.restarted else "started"
        self._ship(f"ray: {name} {what} as pid {self.proc.pid} on node {self.node[:12]} ({self.host})\n".encode())
        self.pump = threading.Thread(target=self._pump, name=f"{name}-log", daemon=True)
        self.pump.start()

    def _ship(self, data: bytes) -> None:
        self.sink.write.remote(self.name, data)   # in order: one caller, one sequential sink

    def _pump(self) -> None:
        fd = self.proc.stdout.fileno()
        while True:
            data = os.read(fd, 65536)
            if not data:
                return
            self._ship(data)

    def info(self) -> dict:
        return {"pid": self.proc.pid, "node": self.node, "host": self.host, "restarted": self.restarted}

    def wait(self) -> int:
        """Block until the service exits; its exit code. A non-zero exit that no ``stop``
        asked for ends this actor's process instead, for Ray to restart."""
        import ray

        code = self.proc.wait()
        kill_group(self.proc.pid, signal.SIGKILL)   # what it left in its group; closes the pipe
        self.pump.join(timeout=5.0)
        restart = code != 0 and not self.stopping
        try:   # the exit reaches the driver's log before this actor ends
            ray.get(self.sink.exited.remote(self.name, self.proc.pid, code, restart), timeout=10.0)
        except Exception:  # noqa: BLE001 - the driver is gone or slow: the restart matters more
            pass
        if restart:
            os._exit(1)   # an unplanned death: Ray's restart policy re-creates this actor
        return code

    def stop(self, deadline_s: float) -> dict:
        """SIGTERM the service's group, SIGKILL after ``deadline_s``; its exit code."""
        self.stopping = True
        killed = False
        if self.proc.poll() is None:
            kill_group(self.proc.pid, signal.SIGTERM)
            try:
                self.proc.wait(timeout=deadline_s)
            except subprocess.TimeoutExpired:
                kill_group(self.proc.pid, signal.SIGKILL)
                killed = True
                self.proc.wait()
        return {"pid": self.proc.pid, "code": self.proc.returncode, "killed": killed}


# ----------------------------------------------------------------- the placement
class _Placed(Member):
    """The driver's view of one service placed as a Ray actor."""

    def __init__(self, spec: ServiceSpec, options: dict):
        super().__init__(spec)
        self.options = options
        self.handle = None
        self.state = "placing"     # placing, running, restarting, done, failed, stopped
        self.since = time.monotonic()
        self._pid: int | None = None
        self.node = self.host = None

    @property
    def pid(self) -> int | None:
        return self._pid


class RayRun(RunDriver):
    """The services of one run as Ray actors: the Ray placement of
    ``deploy.driver.RunDriver`` (which keeps the live line and the run
    directory's records and runs the loop). Ray restarts a crashed service
    (``max_restarts``); this class places, watches and stops them."""

    label, label_error = "ray", "ray driver"
    down_word, down_states = "waiting", ("placing", "restarting", "failed")

    def __init__(self, ray, specs: Sequence[ServiceSpec], run_dir: str | Path, placement: RayPlacement, *,
                 files: dict[str, str], cwd: str, out=None):
        super().__init__([_Placed(s, placement.request(s.name)) for s in specs], run_dir, placement, out=out)
        self.ray, self.placement = ray, placement
        self.services: list[_Placed] = self.members
        self.files, self.cwd = files, cwd
        self.refs: dict = {}       # pending ObjectRef -> (service, "info" | "wait")
        self.sink = None
        self.sink_name = f"sage-logs-{os.getpid()}-{time.time_ns()}"   # unique in this driver's namespace
        self.driver_node = ray.get_runtime_context().get_node_id()

    # ------------------------------------------------------------- records
    def start_fields(self) -> dict:
        return {"placer": "ray", "pid": os.getpid(), "driver_node": self.driver_node}

    def member_status(self, p: _Placed) -> dict:
        return {**super().member_status(p), "node": p.node, "host": p.host, "resources": p.options}

    def summary_extra(self) -> str:
        return f" | nodes {len({p.node for p in self.services if p.state == 'running'})}"

    def idle(self) -> None:
        pass   # poll_members waits in ray.wait

    # ------------------------------------------------------------- placing
    def _on_driver_node(self) -> dict:
        from ray.util.scheduling_strategies import NodeAffinitySchedulingStrategy

        return {"scheduling_strategy": NodeAffinitySchedulingStrategy(self.driver_node, soft=False)}

    def _create(self, p: _Placed) -> None:
        role = role_of(p.spec.name)
        # the router and the learner write or serve what the driver reads: on its node;
        # actors spread over the nodes (Ray would otherwise pack them)
        where = self._on_driver_node() if role in ("router", "learner") else \
            {"scheduling_strategy": "SPREAD"} if role == "actor" else {}
        cls = self.ray.remote(ServiceRunner).options(
            max_restarts=self.placement.max_restarts, max_task_retries=0, max_concurrency=4, **p.options, **where)
        env = {"PYTHONUNBUFFERED": "1"}
        if os.environ.get("PYTHONPATH"):
            env["PYTHONPATH"] = os.environ["PYTHONPATH"]
        p.handle = cls.remote(p.spec.name, list(p.spec.argv), files=self.files, cwd=self.cwd, env=env,
                              sink=self.sink_name, restart_delay_s=self.placement.restart_delay_s)
        p.state, p.since = "placing", time.monotonic()
        self._ask_info(p)

    def _ask_info(self, p: _Placed) -> None:
        self.refs[p.handle.info.remote()] = (p, "info")

    def _wait_ready(self, p: _Placed) -> None:
        """Block until ``p`` is placed and (router) accepts TCP connections."""
        deadline = time.monotonic() + self.placement.placement_timeout_s
        while p.state == "placing" and self.outcome is None and not self.signals:
            if time.monotonic() > deadline:
                self._placement_timeout(p)
                return
            self.poll()
        if p.spec.ready_tcp is None or p.state != "running":
            return
        if not self.wait_ready(p, self.placement.ready_timeout_s, give_up=lambda: bool(self.signals)) \
                and not self.signals:
            host, port = p.spec.ready_tcp
            raise RuntimeError(f"{p.spec.name} did not accept connections on {host}:{port} within "
                               f"{self.placement.ready_timeout_s} s; see {self.paths.log(p.spec.name)}")

    def _placement_timeout(self, p: _Placed) -> None:
        p.state = "failed"
        msg = (f"giving up: Ray could not place {p.spec.name} within {self.placement.placement_timeout_s:g} s "
               f"(it asks for {p.options}; free now: {self.ray.available_resources()})")
        self.event("give_up", service=p.spec.name, message=msg)
        self.finish(EXIT_GAVE_UP, msg)

    def start(self) -> None:
        self.sink = self.ray.remote(LogSink).options(name=self.sink_name, num_cpus=0, max_restarts=0,
                                                     **self._on_driver_node()).remote(str(self.paths.logs))
        first = [p for p in self.services if p.spec.ready_tcp is not None]   # the router: before the rest
        for p in first:
            self._create(p)
            self._wait_ready(p)
        for p in self.services:
            if p.handle is None and self.outcome is None:
                self._create(p)

    # ------------------------------------------------------------- monitoring
    def poll_members(self) -> None:
        """Handle the answers that arrived: placements, (re)starts, exits."""
        if self.refs:
            ready, _ = self.ray.wait(list(self.refs), num_returns=len(self.refs), timeout=self.placement.poll_s)
        else:
            ready = []
            time.sleep(self.placement.poll_s)
        for ref in ready:
            p, kind = self.refs.pop(ref)
            if p.state in ("stopped", "failed"):
                continue
            if kind == "info":
                self._on_info(p, ref)
            else:
                self._on_wait(p, ref)
        now = time.monotonic()
        for p in self.services:
            if p.state == "placing" and now - p.since > self.placement.placement_timeout_s:
                self._placement_timeout(p)

    def _on_info(self, p: _Placed, ref) -> None:
        exc = self.ray.exceptions
        try:
            info = self.ray.get(ref)
        except exc.ActorUnavailableError:      # being re-created: ask again
            self._ask_info(p)
            return
        except exc.RayActorError as e:         # dead for good: restarts spent, or it could not start
            self._gave_up(p, e)
            return
        if p.starts:
            self.event("restart", service=p.spec.name, attempt=p.starts + 1)
        p.starts += 1
        p.state, p._pid, p.node, p.host = "running", info["pid"], info["node"], info["host"]
        self.event("start", service=p.spec.name, pid=p.pid, attempt=p.starts, node=p.node, host=p.host,
                   argv=p.spec.argv)
        self.refs[p.handle.wait.remote()] = (p, "wait")

    def _on_wait(self, p: _Placed, ref) -> None:
        try:
            code = self.ray.get(ref)
        except self.ray.exceptions.RayActorError:
            # the service crashed and took its Ray actor along (or the worker/node was lost)
            last = self._last_exit(p)
            code = last[1] if last and last[0] == p.pid else None
            p.last_code = code
            self.event("exit", service=p.spec.name, pid=p.pid, code=code, node=p.node)
            p.state = "restarting"
            self._ask_info(p)   # answered once Ray has re-created it, or raises when it will not
            return
        p.last_code = code
        self.event("exit", service=p.spec.name, pid=p.pid, code=code, node=p.node)
        p.state = "done"
        if code == 0 and p.spec.ends_run:
            self.finish(0, f"{p.spec.name} finished")

    def _last_exit(self, p: _Placed) -> tuple[int, int] | None:
        try:
            return self.ray.get(self.sink.last_exit.remote(p.spec.name), timeout=10.0)
        except Exception:  # noqa: BLE001 - the exit code is informative only
            return None

    def _gave_up(self, p: _Placed, error: BaseException) -> None:
        p.state = "failed"
        reason = str(error).splitlines()[0] if str(error) else type(error).__name__
        msg = (f"giving up: {p.spec.name} is dead after {max(p.starts - 1, 0)} restart(s) "
               f"(Ray max_restarts {self.placement.max_restarts}; last exit code {p.last_code}): {reason}; "
               f"see {self.paths.log(p.spec.name)}")
        self.event("give_up", service=p.spec.name, code=p.last_code, restarts=max(p.starts - 1, 0), message=msg)
        self.finish(EXIT_GAVE_UP, msg)

    # ------------------------------------------------------------- shutdown
    def stop_wave(self, group: list[_Placed]) -> None:
        """SIGTERM, SIGKILL after the deadline (a second signal skips the wait), then
        kill their Ray actors."""
        group = [p for p in group if p.handle is not None]
        stops = {}
        for p in group:
            if p.state in ("running", "restarting"):
                stops[p.handle.stop.remote(self.placement.term_deadline_s)] = p
                self.event("stop", service=p.spec.name, pid=p.pid, signal="SIGTERM")
        n_signals = len(self.signals)
        deadline = time.monotonic() + self.placement.term_deadline_s + 10.0
        while stops and time.monotonic() < deadline and len(self.signals) == n_signals:
            ready, _ = self.ray.wait(list(stops), num_returns=len(stops), timeout=0.2)
            for ref in ready:
                p = stops.pop(ref)
                try:
                    res = self.ray.get(ref)
                except self.ray.exceptions.RayError:
                    continue
                if res["killed"]:
                    self.event("kill", service=p.spec.name, pid=res["pid"], signal="SIGKILL")
                p.last_code = res["code"]
                self.event("exit", service=p.spec.name, pid=res["pid"], code=res["code"], node=p.node)
        for p in group:   # the Ray actor goes too; its process, if still there, by pdeathsig
            self.ray.kill(p.handle, no_restart=True)
            if p.state != "failed":
                p.state = "stopped"

    def shutdown(self, reason: str = "shutdown") -> None:
        """Stop the services wave by wave (router last), then the log sink."""
        super().shutdown(reason)
        if self.sink is not None:
            try:
                self.ray.get(self.sink.close.remote(), timeout=10.0)
            except Exception:  # noqa: BLE001 - the logs are as complete as they got
                pass
            self.ray.kill(self.sink, no_restart=True)


def run_on_ray(config_path: str | Path, *, placement: RayPlacement | None = None, actors: int | None = None,
               roles: Sequence[str] = ROLES, actor_ids: Sequence[int] | None = None,
               install_signals: bool = True, out=None) -> int:
    """Run the services of the run config at ``config_path`` on the Ray cluster of
    ``placement.address`` until the learner's budget is reached, a signal arrives,
    or a service is dead after its restarts. Returns the exit code (0 = finished).
    A ``ClusterError`` before anything starts when the cluster cannot take the run."""
    placement = placement or RayPlacement()
    out = out if out is not None else sys.stderr
    saved = TrainConfig.load(config_path)
    if actors is not None:
        saved.actors = int(actors)
    ray = connect(placement.address, cpus_for_local(placement, service_names(saved, roles, actor_ids)))
    cfg, specs, child_config = prepare_run(config_path, actors=actors, roles=roles, actor_ids=actor_ids,
                                           absolute=True, who="ray", out=out)
    cluster = check_cluster(ray, placement, [s.name for s in specs])
    files = {str(child_config): Path(child_config).read_text()}
    runner = RayRun(ray, specs, cfg.run_dir, placement, files=files, cwd=os.getcwd(), out=out)
    print(f"ray: run {cfg.run_id} on {cluster['nodes']} node(s) ({', '.join(cluster['hosts'])}), "
          f"{len(specs)} services ({', '.join(s.name for s in specs)}), router {cfg.transport.connect[0]}, "
          f"run dir {cfg.run_dir}", file=out, flush=True)
    return run_with_status(runner, cfg, install_signals)
