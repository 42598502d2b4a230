"""`sage bench learner`: wall time of one learner update per method on the
same synthetic batch, as ratios to HAPPO (same run, same machine)."""
from __future__ import annotations

import statistics
import time

import numpy as np
import torch

from common.algos.config import AlgoConfig
from common.algos.methods import make_method
from common.algos.synthetic import BanditTask, collect

BENCH_METHODS = ("happo", "sail_cbf", "talo_cbf", "sage")


def default_obs_dim() -> tuple[int, str]:
    """The environment's observation size if the env package is importable, else 40."""
    try:
        from common.env import OBS_FEATURE_NAMES  # noqa: PLC0415
        return len(OBS_FEATURE_NAMES), "env"
    except (ImportError, AttributeError):
        return 40, "default"


def bench_learner(T: int = 64, K: int = 32, obs_dim: int | None = None, rows: int = 34,
                  repeats: int = 3, methods=BENCH_METHODS, threads: int = 1, seed: int = 0,
                  progress: float = 0.5) -> dict:
    """Median seconds per ``update`` (after one warm-up update) for each method."""
    if T < 1 or K < 1 or repeats < 1 or rows < 1:
        raise ValueError("bench learner: T, K, rows and repeats must be >= 1")
    if "happo" not in methods:
        raise ValueError("bench learner: ratios are relative to happo; include it")
    source = "argument"
    if obs_dim is None:
        obs_dim, source = default_obs_dim()
    torch.set_num_threads(threads)
    cfg = AlgoConfig(seed=seed)
    task = BanditTask(obs_dim=obs_dim, seed=seed, n_rows=rows, human_rate=0.05)
    times: dict[str, list[float]] = {}
    last_diag: dict[str, dict] = {}
    for name in methods:
        method = make_method(name, cfg, obs_dim, obs_dim * 3)
        # same contexts for every method (same rng seed); proposals are each method's own
        batch = collect(method, task, T, K, progress, np.random.default_rng(seed))
        method.update(batch, progress)                      # warm-up
        times[name] = []
        for _ in range(repeats):
            t0 = time.perf_counter()
            last_diag[name] = method.update(batch, progress)
            times[name].append(time.perf_counter() - t0)
    update_s = {k: statistics.median(v) for k, v in times.items()}
    return {
        "bench": "learner",
        "T": T, "K": K, "samples": T * K, "obs_dim": obs_dim, "obs_dim_source": source,
        "rows": rows, "epochs": cfg.epochs, "minibatches": cfg.minibatches,
        "repeats": repeats, "torch_threads": threads,
        "update_s": update_s,
        "update_s_all": times,
        "ratio_vs_happo": {k: v / update_s["happo"] for k, v in update_s.items()},
        "target": "sage update <= 3x happo update",
        "sage_within_target": (update_s["sage"] / update_s["happo"] <= 3.0) if "sage" in update_s else None,
        "w_gap": {k: d.get("w_gap") for k, d in last_diag.items()},
    }
