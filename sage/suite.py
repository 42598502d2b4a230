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
from services.config import UNLIMITED_UPDATES, TrainConfig


@dataclass(frozen=True)
class Arm:
    """One arm of an experiment: a method with the settings it runs under. A plain
    ``--methods`` suite has one arm per method (named after it, no settings); a
    protocol names its arms and pins their settings (``docs/protocol/table1.toml``)."""
    name: str
    method: str
    settings: tuple[str, ...] = ()     # `sage train --set` items of this arm only
    scenarios: tuple[str, ...] = ()    # where it runs; empty: every scenario of the suite


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
    # per scenario, over updates_per_run (a protocol's budgets)
    updates_by_scenario: dict[str, int] = field(default_factory=dict)
    # deployment episodes per run: >= 100 so a run's SR is graded (steps of 1%), not 0/100%
    eval_episodes: int = 100
    # checkpoints evaluated at the end of each run (eval_episodes each; the mean is the run's figure)
    eval_checkpoints: int = 1
    envs_per_actor: int = 32
    train_overrides: list[str] = field(default_factory=list)   # `sage train --set` items of every run
    workers: int = max(1, os.cpu_count() or 1)
    out_dir: str = "results/suite"
    arms: list[Arm] = field(default_factory=list)   # empty: one arm per method
    protocol: str = ""          # the protocol file this suite runs, if any
    protocol_sha256: str = ""

    def arm_list(self) -> list[Arm]:
        return list(self.arms) or [Arm(m, m) for m in self.methods]


@dataclass(frozen=True)
class RunSpec:
    method: str
    scenario: str
    seed: int
    arm: str = ""

    @property
    def name(self) -> str:
        return f"{self.arm or self.method}__{self.scenario}__seed{self.seed}"


def plan(cfg: SuiteConfig) -> list[RunSpec]:
    arms = cfg.arm_list()
    unknown = [a.method for a in arms if a.method not in ALL_METHODS]
    if unknown or not arms:
        raise ValueError(f"unknown methods {unknown}; choose from {', '.join(ALL_METHODS)}")
    unknown = [s for s in cfg.scenarios + [s for a in arms for s in a.scenarios] if s not in SCENARIOS]
    if unknown or not cfg.scenarios:
        raise ValueError(f"unknown scenarios {unknown}; choose from {', '.join(sorted(SCENARIOS))}, "
                         f"a family ({', '.join(FAMILIES)}) or all")
    names = [a.name for a in arms]
    if len(set(names)) != len(names):
        raise ValueError(f"arm names must be unique, got {names}")
    return [RunSpec(a.method, s, k, a.name if a.name != a.method or a.settings else "")
            for s, k, a in itertools.product(cfg.scenarios, cfg.seeds, arms)
            if not a.scenarios or s in a.scenarios]


def run_config(cfg: SuiteConfig, spec: RunSpec, run_dir: Path) -> TrainConfig:
    """The resolved config of one run: the suite's settings, then the arm's, then the run's
    method, scenario, seed and budget. Each run trains exactly this (``sage train --config``)."""
    arm = {a.name: a for a in cfg.arm_list()}.get(spec.arm or spec.method)
    tc = TrainConfig(run_id=spec.name, run_dir=str(run_dir), method=spec.method, scenario=spec.scenario,
                     seed=spec.seed, envs_per_actor=cfg.envs_per_actor, eval_episodes=cfg.eval_episodes,
                     eval_checkpoints=cfg.eval_checkpoints, minutes=cfg.minutes_per_run)
    tc.updates = cfg.updates_by_scenario.get(spec.scenario) or cfg.updates_per_run or UNLIMITED_UPDATES
    for item in list(cfg.train_overrides) + list(arm.settings if arm else ()):
        apply_override(tc, item)
    return tc.resolve()


def train_command(cfg: SuiteConfig, spec: RunSpec, run_dir: Path) -> list[str]:
    """`sage train` of one run, from the run's config file (written by ``write_run_config``)."""
    return [sys.executable, "-m", "sage", "train", "--config", str(run_dir) + ".config.json", "--quiet"]


def write_run_config(cfg: SuiteConfig, spec: RunSpec, run_dir: Path) -> TrainConfig:
    tc = run_config(cfg, spec, run_dir)
    tc.save(str(run_dir) + ".config.json")
    return tc


def git_commit() -> str:
    """The commit this code is at (``+dirty`` with uncommitted changes), or "" outside a checkout."""
    root = Path(__file__).resolve().parents[1]
    try:
        head = subprocess.run(["git", "-C", str(root), "rev-parse", "HEAD"], capture_output=True, text=True,
                              timeout=10, check=True).stdout.strip()
        dirty = subprocess.run(["git", "-C", str(root), "status", "--porcelain", "--untracked-files=no"],
                               capture_output=True, text=True, timeout=10, check=True).stdout.strip()
    except (OSError, subprocess.SubprocessError):
        return ""
    return head + ("+dirty" if dirty else "")


def collect_result(spec: RunSpec, run_dir: Path, budget: dict, provenance: dict | None = None) -> dict:
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
    record = {
        "method": spec.method, "scenario": spec.scenario, "seed": spec.seed,
        "eval": eval_record(summary["eval"]), "train_curve": curve, "budget": budget,
        "run_dir": str(run_dir),
    }
    if spec.arm:
        record["arm"] = spec.arm
    if "eval_by_checkpoint" in summary:
        record["eval_by_checkpoint"] = [{"version": e.get("version"), **eval_record(e)}
                                        for e in summary["eval_by_checkpoint"]]
    if provenance:
        record.update(provenance)
    return record


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


def run_budget(cfg: SuiteConfig, wall_s: float, spec: RunSpec | None = None) -> dict:
    """The ``budget`` record of a run that took ``wall_s`` seconds."""
    updates = cfg.updates_by_scenario.get(spec.scenario) if spec is not None else None
    return {"minutes": cfg.minutes_per_run, "updates": updates or cfg.updates_per_run, "wall_s": round(wall_s, 1),
            "envs_per_actor": cfg.envs_per_actor, "eval_episodes": cfg.eval_episodes,
            "eval_checkpoints": cfg.eval_checkpoints, "overrides": list(cfg.train_overrides)}


def provenance(cfg: SuiteConfig, spec: RunSpec, run_dir: Path, commit: str) -> dict:
    """What a result rests on: its resolved config's fingerprint, the commit, the protocol."""
    tc = TrainConfig.load(str(run_dir) + ".config.json")
    out = {"fingerprint": tc.fingerprint(), "commit": commit}
    if cfg.protocol:
        out.update(protocol=cfg.protocol, protocol_sha256=cfg.protocol_sha256)
    return out


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
            done.append(Finished(spec, collect_result(spec, run_dir, run_budget(self.cfg, wall, spec))))
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
                  threads: int, driver_node: str, config_text: str) -> dict:
    """One suite run inside a Ray task: its config file written on the task's node (the
    driver's copy may not be there), `sage train` there, then its result record, built
    there (the run directory stays on that node). The log comes back too when that node
    is not the driver's."""
    import ray

    atomic_write_text(run_dir + ".config.json", config_text)
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
        config_text = Path(str(run_dir) + ".config.json").read_text()
        ref = self._task.remote(spec, argv, str(run_dir.resolve()), str(log_path.resolve()),
                                run_budget(self.cfg, 0.0, spec), max(1, int(self.cpus_per_run)), self.driver_node,
                                config_text)
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


def check_resume(cfg: SuiteConfig, planned: list[RunSpec]) -> None:
    """A suite folder holds results of exactly the configs this suite would run: a kept
    result whose config fingerprint differs (another --set, budget, protocol) is a
    ``ValueError`` naming how many and the first, never a mix of two experiments."""
    out = Path(cfg.out_dir)
    stale = []
    for spec in planned:
        path = out / f"{spec.name}.json"
        if not path.exists():
            continue
        try:
            kept = json.loads(path.read_text()).get("fingerprint")
        except (ValueError, OSError, AttributeError):
            kept = None
        if kept != run_config(cfg, spec, out / "runs" / spec.name).fingerprint():
            stale.append(spec.name)
    if stale:
        raise ValueError(f"{out} holds {len(stale)} result(s) of another config (first: {stale[0]}): this suite's "
                         "settings differ from theirs; use another --out, or the settings they were run with")


def run_suite(cfg: SuiteConfig, log=print, progress_out=None, pool=None) -> list[Path]:
    """Run the pending runs of the plan on ``pool`` (default: ``LocalPool``, this
    machine's cores); ``log`` gets one line per event, a progress bar (runs done /
    running / failed, ETA from the mean run time) goes to ``progress_out``
    (default stderr; plain periodic lines when not a terminal). On an interrupt
    (KeyboardInterrupt) the running runs are stopped; the finished ones' results
    are kept, so running the suite again resumes it."""
    out = Path(cfg.out_dir)
    planned = plan(cfg)
    check_resume(cfg, planned)
    (out / "runs").mkdir(parents=True, exist_ok=True)
    atomic_write_text(out / "suite_config.json", json.dumps(asdict(cfg), indent=2))
    pending = [s for s in planned if not (out / f"{s.name}.json").exists()]
    already = len(planned) - len(pending)
    for spec in pending:
        write_run_config(cfg, spec, out / "runs" / spec.name)
    commit = git_commit()
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
                end.record.update(provenance(cfg, end.spec, out / "runs" / end.spec.name, commit))
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
# the flags that define the experiment (a protocol file pins them all instead)
EXPERIMENT_FLAGS = ("methods", "scenarios", "seeds", "minutes_per_run", "updates_per_run", "eval_episodes",
                    "envs_per_actor", "set")


def register(commands, bench) -> None:
    d = SuiteConfig()
    p = commands.add_parser("suite", help="train methods x scenarios x seeds under a budget (resumable)")
    p.add_argument("--protocol", default=None, metavar="FILE",
                   help="run the campaign a protocol file pins (e.g. docs/protocol/table1.toml): arms, scenarios, "
                        "seeds, budgets, evaluation; the experiment flags below are then refused")
    p.add_argument("--pilot", action="store_true",
                   help="with --protocol: run its [pilot] subset (the arms and runs that set the budgets)")
    p.add_argument("--dry-run", action="store_true", help="list the runs (and their config fingerprints), run nothing")
    p.add_argument("--methods", default=None, help=f"comma list (default {','.join(d.methods)})")
    p.add_argument("--scenarios", default=None, help="comma list, a family (LCP/STR/CCN) or 'all' (default)")
    p.add_argument("--seeds", default=None, help=f"comma list (default {','.join(map(str, d.seeds))})")
    p.add_argument("--minutes-per-run", type=positive_float, default=None,
                   help=f"wall-clock budget per run (default {d.minutes_per_run:g})")
    p.add_argument("--updates-per-run", type=positive_int, default=None,
                   help="learner updates per run (same samples for every method); with "
                        "--minutes-per-run, whichever ends first")
    p.add_argument("--eval-episodes", type=nonneg_int, default=None, help=f"(default {d.eval_episodes})")
    p.add_argument("--envs-per-actor", type=positive_int, default=None, help=f"(default {d.envs_per_actor})")
    p.add_argument("--set", action="append", default=None, metavar="SECTION.KEY=VALUE",
                   help="passed to every `sage train` (e.g. --set algo.actor_lr=1e-3)")
    p.add_argument("--workers", type=positive_int, default=None,
                   help="parallel runs (default: cores; with --ray: cluster CPUs / CPUs per run)")
    p.add_argument("--ray", default=None, metavar="ADDRESS",
                   help="run every (method, scenario, seed) as a Ray task on the cluster at ADDRESS: auto, HOST:PORT "
                        "or local (extra .[cluster]); results are still written to --out here")
    p.add_argument("--ray-cpus-per-run", type=positive_float, default=1.0,
                   help="CPUs each run's Ray task asks for (default %(default)s)")
    p.add_argument("--out", default=None, help=f"results folder (default {d.out_dir}; with --protocol "
                                               "results/<protocol name>)")
    p.set_defaults(func=_suite)


def _scenarios(arg: str) -> list[str]:
    if arg == "all":
        return [s for f in FAMILIES.values() for s in f]
    out = []
    for part in filter(None, (p.strip() for p in arg.split(","))):
        out += FAMILIES.get(part, [part])
    return out


def check_train_overrides(items: list[str], context: str = "--set") -> None:
    """Apply the ``--set`` items to a fresh run config, as every `sage train` of
    the suite will: a bad one fails here, once, instead of in every run."""
    cfg = TrainConfig()
    with user_input(context):
        for item in items:
            try:
                apply_override(cfg, item)
            except SystemExit as exc:
                raise ValueError(str(exc.code)) from None
        cfg.resolve()


def suite_config_from_args(args: argparse.Namespace) -> SuiteConfig:
    """The suite of ``--protocol FILE`` or of the experiment flags; bad input is a ``UsageError``."""
    if args.protocol:
        given = [f"--{name.replace('_', '-')}" for name in EXPERIMENT_FLAGS if getattr(args, name) is not None]
        if given:
            raise UsageError(f"--protocol {args.protocol} pins the experiment; drop {', '.join(given)} "
                             "(or edit a copy of the protocol)")
        from sage.protocol import load_protocol   # tomllib only where a protocol is read

        with user_input(f"--protocol {args.protocol}"):
            cfg = load_protocol(args.protocol, out_dir=args.out, pilot=args.pilot).suite
            plan(cfg)
        for arm in cfg.arm_list():
            check_train_overrides(cfg.train_overrides + list(arm.settings), f"--protocol {args.protocol} "
                                                                            f"arm {arm.name}")
        return cfg
    if args.pilot:
        raise UsageError("--pilot runs a protocol's [pilot] subset: give --protocol FILE")
    d = SuiteConfig()
    with user_input():
        cfg = SuiteConfig(
            methods=[m.strip() for m in (args.methods or ",".join(d.methods)).split(",") if m.strip()],
            scenarios=_scenarios(args.scenarios or "all"),
            seeds=int_list(args.seeds, minimum=0, name="--seeds") if args.seeds else d.seeds,
            minutes_per_run=args.minutes_per_run or d.minutes_per_run, updates_per_run=args.updates_per_run,
            eval_episodes=d.eval_episodes if args.eval_episodes is None else args.eval_episodes,
            envs_per_actor=args.envs_per_actor or d.envs_per_actor, out_dir=args.out or d.out_dir,
            train_overrides=list(args.set or []),
        )
        plan(cfg)
    check_train_overrides(cfg.train_overrides)
    return cfg


def dry_run(cfg: SuiteConfig, out=print) -> list[dict]:
    """The runs a suite would start (skipping none), one line each, and as records."""
    rows = []
    for spec in plan(cfg):
        tc = run_config(cfg, spec, Path(cfg.out_dir) / "runs" / spec.name)
        rows.append({"run": spec.name, "arm": spec.arm or spec.method, "method": spec.method,
                     "scenario": spec.scenario, "seed": spec.seed, "updates": tc.updates,
                     "fingerprint": tc.fingerprint(),
                     "done": (Path(cfg.out_dir) / f"{spec.name}.json").exists()})
        out(f"{spec.name:48s} updates {tc.updates:<6d} fingerprint {tc.fingerprint()}"
            + ("  (done)" if rows[-1]["done"] else ""))
    arms = sorted({r["arm"] for r in rows})
    out(f"{len(rows)} runs: {len(arms)} arms x {len(cfg.scenarios)} scenarios x {len(cfg.seeds)} seeds "
        f"(arms limited to some scenarios run fewer); results in {cfg.out_dir}")
    return rows


def _suite(args: argparse.Namespace) -> int:
    cfg = suite_config_from_args(args)
    if args.dry_run:
        dry_run(cfg)
        return 0
    out = Path(cfg.out_dir)
    if out.exists() and not out.is_dir():
        raise UsageError(f"--out {out} exists and is not a directory")
    if args.workers:
        cfg.workers = args.workers
    pool = None
    with user_input():
        check_resume(cfg, plan(cfg))
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
