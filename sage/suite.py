"""`sage suite`: methods × scenarios × seeds under a budget, resumable, spread over cores.

Each run is an independent `sage train` subprocess (its own in-process
services, one core's worth of work) followed by a deployment evaluation; the
suite then writes one JSON result per run (the schema `sage.report` reads).
A run whose result file exists is skipped, so an interrupted suite resumes
where it stopped. Runs are scheduled over ``--workers`` parallel slots
(default: the number of cores).
"""
from __future__ import annotations

import argparse
import heapq
import itertools
import json
import os
import subprocess
import sys
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

from common.algos.registry import ALL_METHODS, METHODS
from common.env.scenarios import FAMILIES, SCENARIOS
from common.rundir import RunDir, atomic_write_text, read_jsonl
from common.status import Progress
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


def run_suite(cfg: SuiteConfig, log=print, progress_out=None) -> list[Path]:
    """Run the pending runs of the plan; ``log`` gets one line per event, a
    progress bar (runs done / running / failed, ETA from the mean run time) goes
    to ``progress_out`` (default stderr; plain periodic lines when not a terminal)."""
    out = Path(cfg.out_dir)
    (out / "runs").mkdir(parents=True, exist_ok=True)
    atomic_write_text(out / "suite_config.json", json.dumps(asdict(cfg), indent=2))
    planned = plan(cfg)
    pending = [s for s in planned if not (out / f"{s.name}.json").exists()]
    already = len(planned) - len(pending)
    log(f"suite: {already} done, {len(pending)} to run on {cfg.workers} workers")
    running: dict[RunSpec, tuple[subprocess.Popen, float]] = {}
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
        bar.update(already + len(written), running=len(running), failed=failures,
                   eta_s=suite_eta(mean, len(pending), [now - t for _, t in running.values()], cfg.workers))

    # A single-threaded torch per run keeps `workers` runs from oversubscribing the cores.
    env = dict(os.environ, OMP_NUM_THREADS="1", MKL_NUM_THREADS="1")
    while pending or running:
        while pending and len(running) < cfg.workers:
            spec = pending.pop(0)
            run_dir = out / "runs" / spec.name
            log_file = open(out / "runs" / f"{spec.name}.log", "w")
            proc = subprocess.Popen(train_command(cfg, spec, run_dir), stdout=log_file,
                                    stderr=subprocess.STDOUT, env=env)
            running[spec] = (proc, time.time())
        show()
        time.sleep(1.0)
        for spec, (proc, started) in list(running.items()):
            if proc.poll() is None:
                continue
            del running[spec]
            run_dir = out / "runs" / spec.name
            if proc.returncode != 0:
                failures += 1
                say(f"suite: {spec.name} FAILED (exit {proc.returncode}); see {run_dir}.log")
                continue
            budget = {"minutes": cfg.minutes_per_run, "updates": cfg.updates_per_run,
                      "wall_s": round(time.time() - started, 1),
                      "envs_per_actor": cfg.envs_per_actor, "eval_episodes": cfg.eval_episodes,
                      "overrides": list(cfg.train_overrides)}
            record = collect_result(spec, run_dir, budget)
            # atomic: a half-written result never counts as done
            path = atomic_write_text(out / f"{spec.name}.json", json.dumps(record, indent=1))
            written.append(path)
            run_times.append(budget["wall_s"])
            ev = record["eval"]
            say(f"suite: {spec.name} SR={ev.get('success_rate', float('nan')):.2f} "
                f"Col/1k={ev.get('col_per_1k', float('nan')):.1f} ({budget['wall_s']:.0f}s)")
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
    p.add_argument("--workers", type=positive_int, default=None, help="parallel runs (default: cores)")
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
    run_suite(cfg)
    return 0
