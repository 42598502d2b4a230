"""`sage suite`: methods × scenarios × seeds under a budget, resumable, spread over cores.

Each run is an independent `sage train` subprocess (its own in-process
services, one core's worth of work) followed by a deployment evaluation; the
suite then writes one JSON result per run (the schema `sage.report` reads).
A run whose result file exists is skipped, so an interrupted suite resumes
where it stopped. Runs are scheduled over ``--workers`` parallel slots
(default: the number of cores), on this machine (``LocalPool``) or, with
``--ray ADDRESS``, as Ray tasks of ``--ray-cpus-per-run`` CPUs each on a Ray
cluster (``RayPool``; default slots: the cluster's CPUs / CPUs per run). Either
way the result files are written here, by this process.
"""
from __future__ import annotations

import argparse
import heapq
import itertools
import json
import os
import signal
import subprocess
import sys
import threading
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import NamedTuple

from common.algos.registry import ALL_METHODS, METHODS
from common.env.scenarios import FAMILIES, SCENARIOS
from common.rundir import RunDir, atomic_write_text, read_jsonl
from common.status import Progress
from deploy import ray_run
from sage.errors import UsageError, int_list, nonneg_int, positive_float, positive_int, user_input
from sage.evaluate import eval_record
from sage.report import CURVE_KEYS
from sage.train import apply_override
from services.config import TrainConfig


@dataclass
class SuiteConfig:
    methods: list[str] = field(default_factory=lambda: list(METHODS))
    scenarios: list[str] = field(default_factory=lambda: [s for f in FAMILIES.values() for s in f])
    seeds: list[int] = field(default_factory=lambda: [0, 1])
    minutes_per_run: float = 5.0
    # A sample budget (learner updates) makes methods comparable on a loaded machine,
    # where a wall-clock budget gives the slower updates fewer samples; both may be set
    # (whichever ends first).
    updates_per_run: int | None = None
    # deployment episodes per run: >= 100 so a run's SR is graded (steps of 1%), not 0/100%
    eval_episodes: int = 100
    envs_per_actor: int = 32
    train_overrides: list[str] = field(default_factory=list)   # `sage train --set` items
    workers: int = max(1, os.cpu_count() or 1)
    out_dir: str = "results/suite"


@dataclass(frozen=True)
class RunSpec:
    method: str
    scenario: str
    seed: int

    @property
    def name(self) -> str:
        return f"{self.method}__{self.scenario}__seed{self.seed}"


def plan(cfg: SuiteConfig) -> list[RunSpec]:
    unknown = [m for m in cfg.methods if m not in ALL_METHODS]
    if unknown or not cfg.methods:
        raise ValueError(f"unknown methods {unknown}; choose from {', '.join(ALL_METHODS)}")
    unknown = [s for s in cfg.scenarios if s not in SCENARIOS]
    if unknown or not cfg.scenarios:
        raise ValueError(f"unknown scenarios {unknown}; choose from {', '.join(sorted(SCENARIOS))}, "
                         f"a family ({', '.join(FAMILIES)}) or all")
    return [RunSpec(m, s, k) for s, k, m in itertools.product(cfg.scenarios, cfg.seeds, cfg.methods)]


def train_command(cfg: SuiteConfig, spec: RunSpec, run_dir: Path) -> list[str]:
    updates = ["--updates", str(cfg.updates_per_run)] if cfg.updates_per_run else []
    return [
        sys.executable, "-m", "sage", "train",
        "--method", spec.method, "--scenario", spec.scenario, "--seed", str(spec.seed),
        "--minutes", str(cfg.minutes_per_run), "--envs-per-actor", str(cfg.envs_per_actor),
        "--eval-episodes", str(cfg.eval_episodes), "--run-dir", str(run_dir), "--quiet",
    ] + updates + [arg for item in cfg.train_overrides for arg in ("--set", item)]


def collect_result(spec: RunSpec, run_dir: Path, budget: dict) -> dict:
    """Build the report's result record from a finished run directory."""
    run = RunDir(run_dir)
    summary = json.loads(run.summary.read_text()) if run.summary.exists() else {}
    if "eval" not in summary:
        raise FileNotFoundError(f"{run_dir}: summary.json has no final evaluation (training did not finish)")
    curve = []
    rows = read_jsonl(run.metrics_jsonl)
    if rows:
        total = max((r.get("env_steps", 0) for r in rows), default=0) or 1
        for r in rows:
            point = dict(r)
            point.setdefault("progress", r.get("env_steps", 0) / total)
            # the report's curve names <- the learner's metric names
            for name, source in CURVE_KEYS.items():
                if source in r:
                    point[name] = r[source]
            curve.append(point)
    return {
        "method": spec.method, "scenario": spec.scenario, "seed": spec.seed,
        "eval": eval_record(summary["eval"]), "train_curve": curve, "budget": budget,
        "run_dir": str(run_dir),
    }


def suite_eta(mean_run_s: float | None, pending: int, running_elapsed: list[float], workers: int) -> float | None:
    """Seconds until the suite ends if every run takes ``mean_run_s``: each running
    run ends after what is left of the mean, the pending runs queue over the
    ``workers`` slots. ``None`` before any run has finished (no mean yet)."""
    if mean_run_s is None:
        return None
    slots = [max(mean_run_s - e, 0.0) for e in running_elapsed]
    slots += [0.0] * max(workers - len(slots), 0)
    heapq.heapify(slots)
    for _ in range(pending):
        heapq.heappush(slots, heapq.heappop(slots) + mean_run_s)
    return max(slots, default=0.0)


def run_budget(cfg: SuiteConfig, wall_s: float) -> dict:
    """The ``budget`` record of a run that took ``wall_s`` seconds."""
    return {"minutes": cfg.minutes_per_run, "updates": cfg.updates_per_run, "wall_s": round(wall_s, 1),
            "envs_per_actor": cfg.envs_per_actor, "eval_episodes": cfg.eval_episodes,
            "overrides": list(cfg.train_overrides)}


class Finished(NamedTuple):
    """A run that ended: its result record (None when it failed) and, if it failed, why."""
    spec: RunSpec
    record: dict | None
    error: str = ""


class LocalPool:
    """Runs on this machine: one `sage train` subprocess per slot."""

    def __init__(self, cfg: SuiteConfig):
        self.cfg, self.slots = cfg, cfg.workers
        self.running: dict[RunSpec, float] = {}   # run -> start time
        self._procs: dict[RunSpec, subprocess.Popen] = {}
        # A single-threaded torch per run keeps `workers` runs from oversubscribing the cores.
        self._env = dict(os.environ, OMP_NUM_THREADS="1", MKL_NUM_THREADS="1")

    def describe(self) -> str:
        return f"{self.slots} workers"

    def start(self, spec: RunSpec, run_dir: Path, log_path: Path) -> None:
        with open(log_path, "w") as log_file:
            self._procs[spec] = subprocess.Popen(train_command(self.cfg, spec, run_dir), stdout=log_file,
                                                 stderr=subprocess.STDOUT, env=self._env)
        self.running[spec] = time.time()

    def finished(self, wait_s: float) -> list[Finished]:
        time.sleep(wait_s)
        done = []
        for spec, proc in list(self._procs.items()):
            if proc.poll() is None:
                continue
            del self._procs[spec]
            wall = time.time() - self.running.pop(spec)
            if proc.returncode != 0:
                done.append(Finished(spec, None, f"exit {proc.returncode}"))
                continue
            run_dir = Path(self.cfg.out_dir) / "runs" / spec.name
            done.append(Finished(spec, collect_result(spec, run_dir, run_budget(self.cfg, wall))))
        return done

    def cancel(self) -> None:
        """Stop the runs still going (an interrupted suite); they rerun on resume."""
        for proc in self._procs.values():
            proc.terminate()
        for proc in self._procs.values():
            try:
                proc.wait(timeout=10)
            except subprocess.TimeoutExpired:
                proc.kill()
        self._procs.clear()
        self.running.clear()


def train_on_node(spec: RunSpec, argv: list[str], run_dir: str, log_path: str, budget: dict,
                  threads: int, driver_node: str) -> dict:
    """One suite run inside a Ray task: `sage train` on the task's node, then its
    result record, built there (the run directory stays on that node). The log
    comes back too when that node is not the driver's."""
    import ray

    env = dict(os.environ, OMP_NUM_THREADS=str(threads), MKL_NUM_THREADS=str(threads))
    started = time.time()
    code = ray_run.run_logged(argv, log_path, env)
    wall = time.time() - started
    node = ray.get_runtime_context().get_node_id()
    log_text = Path(log_path).read_text(errors="replace")[-1_000_000:] if node != driver_node else None
    record = collect_result(spec, Path(run_dir), {**budget, "wall_s": round(wall, 1)}) if code == 0 else None
    return {"code": code, "record": record, "log": log_text}


class RayPool:
    """Runs as Ray tasks on a cluster, ``cpus_per_run`` CPUs each. A task whose
    worker or node is lost is retried by Ray; a cancelled one kills its run."""

    def __init__(self, cfg: SuiteConfig, address: str, cpus_per_run: float = 1.0, slots: int | None = None):
        self.cfg, self.cpus_per_run = cfg, cpus_per_run
        self.ray = ray_run.connect(address)
        total = self.ray.cluster_resources().get("CPU", 0.0)
        if total < cpus_per_run:
            raise ray_run.ClusterError(f"--ray-cpus-per-run {cpus_per_run:g}: the cluster has {total:g} CPUs")
        # one task per slot: Ray starts what it is given, so "running" means running
        self.slots = slots or max(1, int(total // cpus_per_run))
        self.driver_node = self.ray.get_runtime_context().get_node_id()
        self._task = self.ray.remote(train_on_node).options(num_cpus=cpus_per_run, max_retries=2)
        self._refs: dict = {}   # ObjectRef -> run
        self.running: dict[RunSpec, float] = {}

    def describe(self) -> str:
        n = len([node for node in self.ray.nodes() if node.get("Alive")])
        return f"{self.slots} Ray slots ({self.cpus_per_run:g} CPU each, {n} node(s))"

    def start(self, spec: RunSpec, run_dir: Path, log_path: Path) -> None:
        argv = train_command(self.cfg, spec, run_dir.resolve())
        ref = self._task.remote(spec, argv, str(run_dir.resolve()), str(log_path.resolve()),
                                run_budget(self.cfg, 0.0), max(1, int(self.cpus_per_run)), self.driver_node)
        self._refs[ref] = spec
        self.running[spec] = time.time()

    def finished(self, wait_s: float) -> list[Finished]:
        if not self._refs:
            time.sleep(wait_s)
            return []
        ready, _ = self.ray.wait(list(self._refs), num_returns=len(self._refs), timeout=wait_s)
        done = []
        for ref in ready:
            spec = self._refs.pop(ref)
            del self.running[spec]
            try:
                res = self.ray.get(ref)
            except self.ray.exceptions.RayError as exc:   # the task raised, or its retries ran out
                done.append(Finished(spec, None, str(exc).strip().splitlines()[-1][:300]))
                continue
            if res["log"] is not None:   # the run's node is not this one: keep its log here too
                atomic_write_text(Path(self.cfg.out_dir) / "runs" / f"{spec.name}.log", res["log"])
            error = "" if res["code"] == 0 else f"exit {res['code']}"
            done.append(Finished(spec, res["record"], error))
        return done

    def cancel(self) -> None:
        """Cancel the runs still going (an interrupted suite); they rerun on resume."""
        for ref in self._refs:
            self.ray.cancel(ref, force=True)   # kills the task's worker; its `sage train` dies with it
        self._refs.clear()
        self.running.clear()


def run_suite(cfg: SuiteConfig, log=print, progress_out=None, pool=None) -> list[Path]:
    """Run the pending runs of the plan on ``pool`` (default: ``LocalPool``, this
    machine's cores); ``log`` gets one line per event, a progress bar (runs done /
    running / failed, ETA from the mean run time) goes to ``progress_out``
    (default stderr; plain periodic lines when not a terminal). On an interrupt
    (KeyboardInterrupt) the running runs are stopped; the finished ones' results
    are kept, so running the suite again resumes it."""
    out = Path(cfg.out_dir)
    (out / "runs").mkdir(parents=True, exist_ok=True)
    atomic_write_text(out / "suite_config.json", json.dumps(asdict(cfg), indent=2))
    planned = plan(cfg)
    pending = [s for s in planned if not (out / f"{s.name}.json").exists()]
    already = len(planned) - len(pending)
    pool = pool if pool is not None else LocalPool(cfg)
    log(f"suite: {already} done, {len(pending)} to run on {pool.describe()}"
        + (" (finished runs are kept, not rerun)" if already else ""))
    written: list[Path] = []
    failures = 0
    run_times: list[float] = []
    bar = Progress(progress_out if progress_out is not None else sys.stderr, len(planned), "suite", unit="runs")

    def say(msg: str) -> None:   # the bar steps aside for each event line
        bar.clear()
        log(msg)

    def show() -> None:
        mean = sum(run_times) / len(run_times) if run_times else None
        now = time.time()
        bar.update(already + len(written), running=len(pool.running), failed=failures,
                   eta_s=suite_eta(mean, len(pending), [now - t for t in pool.running.values()], pool.slots))

    try:
        while pending or pool.running:
            while pending and len(pool.running) < pool.slots:
                spec = pending.pop(0)
                pool.start(spec, out / "runs" / spec.name, out / "runs" / f"{spec.name}.log")
            show()
            for end in pool.finished(1.0):
                if end.record is None:
                    failures += 1
                    say(f"suite: {end.spec.name} FAILED ({end.error}); see {out / 'runs' / end.spec.name}.log")
                    continue
                # atomic: a half-written result never counts as done
                path = atomic_write_text(out / f"{end.spec.name}.json", json.dumps(end.record, indent=1))
                written.append(path)
                run_times.append(end.record["budget"]["wall_s"])
                ev = end.record["eval"]
                say(f"suite: {end.spec.name} SR={ev.get('success_rate', float('nan')):.2f} "
                    f"Col/1k={ev.get('col_per_1k', float('nan')):.1f} ({end.record['budget']['wall_s']:.0f}s)")
    except KeyboardInterrupt:
        bar.clear()
        log(f"suite: interrupted; {already + len(written)} of {len(planned)} results kept, "
            f"{len(pool.running)} unfinished stopped; run the same command again to resume")
        raise
    finally:
        pool.cancel()
    show()
    bar.close()
    if failures:
        log(f"suite: {failures} runs failed")
    return written


# ----------------------------------------------------------------- command line
def register(commands, bench) -> None:
    d = SuiteConfig()
    p = commands.add_parser("suite", help="train methods x scenarios x seeds under a budget (resumable)")
    p.add_argument("--methods", default=",".join(d.methods))
    p.add_argument("--scenarios", default="all", help="comma list, a family (LCP/STR/CCN) or 'all'")
    p.add_argument("--seeds", default=",".join(map(str, d.seeds)))
    p.add_argument("--minutes-per-run", type=positive_float, default=d.minutes_per_run)
    p.add_argument("--updates-per-run", type=positive_int, default=d.updates_per_run,
                   help="learner updates per run (same samples for every method); with "
                        "--minutes-per-run, whichever ends first")
    p.add_argument("--eval-episodes", type=nonneg_int, default=d.eval_episodes)
    p.add_argument("--envs-per-actor", type=positive_int, default=d.envs_per_actor)
    p.add_argument("--set", action="append", default=[], metavar="SECTION.KEY=VALUE",
                   help="passed to every `sage train` (e.g. --set algo.actor_lr=1e-3)")
    p.add_argument("--workers", type=positive_int, default=None,
                   help="parallel runs (default: cores; with --ray: cluster CPUs / CPUs per run)")
    p.add_argument("--ray", default=None, metavar="ADDRESS",
                   help="run every (method, scenario, seed) as a Ray task on the cluster at ADDRESS: auto, HOST:PORT "
                        "or local (extra .[cluster]); results are still written to --out here")
    p.add_argument("--ray-cpus-per-run", type=positive_float, default=1.0,
                   help="CPUs each run's Ray task asks for (default %(default)s)")
    p.add_argument("--out", default=d.out_dir)
    p.set_defaults(func=_suite)


def _scenarios(arg: str) -> list[str]:
    if arg == "all":
        return [s for f in FAMILIES.values() for s in f]
    out = []
    for part in filter(None, (p.strip() for p in arg.split(","))):
        out += FAMILIES.get(part, [part])
    return out


def check_train_overrides(items: list[str]) -> None:
    """Apply the ``--set`` items to a fresh run config, as every `sage train` of
    the suite will: a bad one fails here, once, instead of in every run."""
    cfg = TrainConfig()
    for item in items:
        apply_override(cfg, item)
    with user_input("--set"):
        cfg.resolve()


def _suite(args: argparse.Namespace) -> int:
    with user_input():
        cfg = SuiteConfig(
            methods=[m.strip() for m in args.methods.split(",") if m.strip()],
            scenarios=_scenarios(args.scenarios),
            seeds=int_list(args.seeds, minimum=0, name="--seeds"), minutes_per_run=args.minutes_per_run,
            updates_per_run=args.updates_per_run,
            eval_episodes=args.eval_episodes, envs_per_actor=args.envs_per_actor, out_dir=args.out,
            train_overrides=list(args.set),
        )
        plan(cfg)
    check_train_overrides(cfg.train_overrides)
    out = Path(cfg.out_dir)
    if out.exists() and not out.is_dir():
        raise UsageError(f"--out {out} exists and is not a directory")
    if args.workers:
        cfg.workers = args.workers
    pool = None
    if args.ray is not None:
        with user_input():   # no Ray, a bad address, too few CPUs: one line, exit 2
            pool = RayPool(cfg, args.ray, args.ray_cpus_per_run, slots=args.workers)
        cfg.workers = pool.slots
    # Ctrl-C or SIGTERM: the running runs are stopped, the finished results kept (exit 128 + signal)
    interrupted: list[int] = []

    def on_signal(signum, _frame):
        interrupted.append(signum)
        raise KeyboardInterrupt

    # signal handlers can only be set in the main thread
    signals = (signal.SIGINT, signal.SIGTERM) if threading.current_thread() is threading.main_thread() else ()
    old = {sig: signal.signal(sig, on_signal) for sig in signals}
    try:
        run_suite(cfg, pool=pool)
    except KeyboardInterrupt:
        return 128 + (interrupted[0] if interrupted else signal.SIGINT)
    finally:
        for sig, handler in old.items():
            signal.signal(sig, handler)
    return 0
