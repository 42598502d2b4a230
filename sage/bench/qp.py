"""`sage bench qp`: amortized cost of the joint CBF-QP shield (Eq. qpshield).

Times every backend of common.shield.qp on one batch of random CBF-like problems
(common.shield.random_problems) and, in the same run, a plain loop that builds and solves a
fresh OSQP problem per QP with default settings; prints same-run ratios.
Numba compile time is excluded (one warm-up call per backend first).
"""
from __future__ import annotations

import argparse
import json
import time
from dataclasses import dataclass

import numpy as np

from common.shield.qp import BACKENDS, DEFAULT_BACKEND, qp_violation, solve_cbf_qp
from common.shield.random_problems import random_cbf_problems
from sage.bench.machine import machine
from sage.errors import nonneg_int, positive_int

TARGET_US_PER_QP = 20.0  # issue 2: default backend, batch 256, one core


@dataclass
class QPBenchConfig:
    batch: int = 256
    rows: int = 34
    d: int = 9
    repeats: int = 20
    seed: int = 0
    violated_frac: float = 1 / 3


def _time_per_qp(fn, n_qp: int, repeats: int) -> dict:
    """Median/min wall and CPU (this thread) microseconds per QP over `repeats` calls."""
    wall, cpu = [], []
    for _ in range(repeats):
        t0, c0 = time.perf_counter(), time.thread_time()
        fn()
        wall.append(time.perf_counter() - t0)
        cpu.append(time.thread_time() - c0)
    scale = 1e6 / n_qp
    return {"us_per_qp": float(np.median(wall)) * scale, "us_per_qp_min": float(np.min(wall)) * scale,
            "us_per_qp_cpu": float(np.median(cpu)) * scale}


def _fresh_osqp_loop(a, C, c, lo=-1.0, hi=1.0) -> np.ndarray:
    """One brand-new OSQP problem per QP: build, setup, solve (default settings)."""
    import osqp
    import scipy.sparse as sp

    B, M, d = C.shape
    P = sp.eye(d, format="csc")
    out = np.empty((B, d))
    for b in range(B):
        A = sp.csc_matrix(np.vstack([C[b], np.eye(d)]))
        l = np.concatenate([c[b], np.full(d, lo)])
        u = np.concatenate([np.full(M, np.inf), np.full(d, hi)])
        prob = osqp.OSQP()
        prob.setup(P, -a[b], A, l, u, verbose=False)
        out[b] = prob.solve(raise_error=False).x
    return out


def run_qp_bench(cfg: QPBenchConfig) -> dict:
    rng = np.random.default_rng(cfg.seed)
    a, C, c, _ = random_cbf_problems(rng, cfg.batch, cfg.rows, cfg.d, cfg.violated_frac)
    results, timings = {}, {}
    for name in BACKENDS:
        results[name] = solve_cbf_qp(a, C, c, backend=name)  # warm-up: numba compile / cache load
        timings[name] = _time_per_qp(lambda: solve_cbf_qp(a, C, c, backend=name), cfg.batch,
                                     cfg.repeats if name == DEFAULT_BACKEND else max(1, cfg.repeats // 5))
    _fresh_osqp_loop(a[:2], C[:2], c[:2])
    loop_x = _fresh_osqp_loop(a, C, c)
    loop_t = _time_per_qp(lambda: _fresh_osqp_loop(a, C, c), cfg.batch, max(1, cfg.repeats // 5))
    ref = results[DEFAULT_BACKEND]
    max_abs_diff = max(float(np.abs(r.a_exec - ref.a_exec).max()) for r in results.values())
    default_us = timings[DEFAULT_BACKEND]["us_per_qp"]
    ratios = {f"{name}_over_default": t["us_per_qp"] / default_us for name, t in timings.items()
              if name != DEFAULT_BACKEND}
    ratios["osqp_loop_over_default"] = loop_t["us_per_qp"] / default_us
    default_cpu = timings[DEFAULT_BACKEND]["us_per_qp_cpu"]
    ratios_cpu = {key: value for key, value in (
        *((f"{n}_over_default", t["us_per_qp_cpu"] / default_cpu) for n, t in timings.items() if n != DEFAULT_BACKEND),
        ("osqp_loop_over_default", loop_t["us_per_qp_cpu"] / default_cpu))}
    return {
        "bench": "qp",
        "default_backend": DEFAULT_BACKEND,
        "backends": {name: t["us_per_qp"] for name, t in timings.items()},
        "backend_timings": timings,
        "osqp_loop_us_per_qp": loop_t["us_per_qp"],
        "osqp_loop_timings": loop_t,
        "ratios": ratios,
        "ratios_cpu": ratios_cpu,
        "max_abs_diff": max_abs_diff,
        "osqp_loop_max_abs_diff_vs_default": float(np.abs(loop_x - ref.a_exec).max()),
        "max_kkt_residual": {name: float(r.kkt_residual.max()) for name, r in results.items()},
        "status_counts": {name: np.bincount(r.status, minlength=3).tolist() for name, r in results.items()},
        "instances": {
            "batch": cfg.batch, "rows": cfg.rows, "d": cfg.d, "seed": cfg.seed,
            "rows_violated_at_proposal_mean": float((np.einsum("bmd,bd->bm", C, a) < c).sum(1).mean()),
            "rows_active_at_solution_mean": float(ref.active.sum(1).mean()),
            "proposal_violation_mean": float(qp_violation(a, C, c).mean()),
            "iterations_mean": float(ref.iterations.mean()),
        },
        "target_us_per_qp": TARGET_US_PER_QP,
        # Judged on this thread's CPU time: on a shared, oversubscribed machine the
        # wall clock also counts time the core spent on other processes.
        "meets_target": default_cpu <= TARGET_US_PER_QP,
        "meets_target_wall": default_us <= TARGET_US_PER_QP,
        "timing": ("median wall-clock over repeats, single thread; us_per_qp_cpu is this thread's CPU "
                   "time (robust to other load on the machine)"),
        "numba_compile_excluded": True,
        "warmup": "one untimed call per backend (numba compile or cache load) before timing",
        "osqp_loop_settings": "osqp.OSQP(); setup(..., verbose=False) defaults; solve() per QP",
        "machine": machine(),
    }


def _handler(args: argparse.Namespace) -> int:
    cfg = QPBenchConfig(batch=args.batch, rows=args.rows, repeats=args.repeats, seed=args.seed)
    out = run_qp_bench(cfg)
    if args.json:
        print(json.dumps(out, indent=2))
    else:
        print(f"QP shield bench: batch {cfg.batch}, d={cfg.d}, M={cfg.rows} "
              f"({out['instances']['rows_violated_at_proposal_mean']:.1f} rows violated at the proposal, "
              f"{out['instances']['rows_active_at_solution_mean']:.1f} active at the solution)")
        print(f"  {'':<16} {'wall':>9}        {'cpu':>9}")
        for name, t in out["backend_timings"].items():
            mark = " (default)" if name == out["default_backend"] else ""
            print(f"  {name:<16} {t['us_per_qp']:9.2f} us/QP  {t['us_per_qp_cpu']:9.2f} us/QP{mark}")
        loop = out["osqp_loop_timings"]
        print(f"  {'fresh OSQP loop':<16} {loop['us_per_qp']:9.2f} us/QP  {loop['us_per_qp_cpu']:9.2f} us/QP")
        for key, value in out["ratios"].items():
            print(f"  ratio {key}: {value:.1f}x wall, {out['ratios_cpu'][key]:.1f}x cpu")
        print(f"  max |a_exec| disagreement between backends: {out['max_abs_diff']:.2e}")
        print(f"  target <= {TARGET_US_PER_QP} us/QP for the default (cpu time): "
              f"{'met' if out['meets_target'] else 'NOT met'}; wall: "
              f"{'met' if out['meets_target_wall'] else 'NOT met'} (numba compile excluded)")
    return 0


def register(commands, bench) -> None:
    p = bench.add_parser("qp", help="joint CBF-QP shield: us per QP per backend vs a fresh-OSQP loop")
    defaults = QPBenchConfig()
    p.add_argument("--json", action="store_true", help="print JSON")
    p.add_argument("--batch", type=positive_int, default=defaults.batch, help="QPs per batch")
    p.add_argument("--rows", type=positive_int, default=defaults.rows, help="safety rows M per QP")
    p.add_argument("--repeats", type=positive_int, default=defaults.repeats, help="timed batches (default backend)")
    p.add_argument("--seed", type=nonneg_int, default=defaults.seed)
    p.set_defaults(func=_handler)
