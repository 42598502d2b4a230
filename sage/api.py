"""The Python API, for notebooks and scripts: the same runs as the CLI.

    from sage.api import TrainConfig, train, evaluate

    run = train(TrainConfig(scenario="maze", method="happo_cbf", updates=50),
                overrides={"algo.actor_lr": 3e-4})
    run.run_dir, run.summary["eval"]["success_rate"]
    evaluate(run.run_dir, episodes=30)["success_rate"]

``train`` takes the config dataclass the CLI builds (``services.config.TrainConfig``;
its fields and ranges are the CLI's flags and ``--set`` keys), writes the same run
directory as ``sage train`` (``config.json``, ``metrics.jsonl``/``.csv``,
``checkpoints/``, ``summary.json`` with the final deployment evaluation) and
returns where it is with the summary. ``evaluate`` is ``sage eval``'s deployment
evaluation (hard trees + exact QP) of a run directory or checkpoint. Bad values
raise ``ValueError`` naming the field.
"""
from __future__ import annotations

import copy
import dataclasses
from dataclasses import dataclass
from pathlib import Path

from common.algos.registry import method_spec
from common.evaluation.deployment import evaluate_policy
from sage.evaluate import eval_record
from sage.runs import load_run
from sage.train import train_run
from services.config import FINAL_EVAL_SEED, TrainConfig

__all__ = ["TrainConfig", "TrainResult", "train", "evaluate"]


@dataclass
class TrainResult:
    run_dir: Path
    summary: dict
    config: TrainConfig


def train(config: TrainConfig | None = None, *, overrides: dict | None = None, mode: str = "inprocess",
          progress: bool = False) -> TrainResult:
    """Train ``config`` (default: ``TrainConfig()``, the main job) with ``overrides``
    ({"algo.actor_lr": 3e-4, "env.max_steps": 300, "seed": 2}) applied on top. ``mode``:
    "inprocess" (threads of this process) or "supervised" (processes). The caller's
    config object is not modified; the resolved one is ``TrainResult.config``."""
    cfg = copy.deepcopy(config) if config is not None else TrainConfig()
    for path, value in (overrides or {}).items():
        cfg.set(path, value)
    if mode not in ("inprocess", "supervised"):
        raise ValueError(f"mode must be inprocess or supervised, got {mode!r}")
    cfg.mode = mode
    if mode == "supervised":
        cfg.actor.exit_on_unhealthy = True   # let the supervisor see and restart it
    cfg.resolve()
    code, summary = train_run(cfg, mode, progress=progress)
    if summary is None:
        raise RuntimeError(f"training {cfg.run_dir} ended with exit code {code}")
    return TrainResult(Path(cfg.run_dir), summary, cfg)


def evaluate(run: str | Path, episodes: int = 30, *, seed: int | None = None, scenario: str | None = None,
             human_slot: int | None = None, shielded: bool | None = None) -> dict:
    """Deployment evaluation of the newest checkpoint of ``run`` (a run directory or a
    checkpoint file): the deterministic trees and, when ``shielded`` (default: as
    trained), the exact QP; ``sage eval``'s record (success_rate, col_per_1k, ...).
    ``seed`` defaults to the run's own final-evaluation episodes (held out from training)."""
    cfg, params, version = load_run(run)
    env_cfg = cfg.env_config()
    if scenario is not None or human_slot is not None:
        env_cfg = dataclasses.replace(env_cfg, scenario=scenario or env_cfg.scenario,
                                      human_slot=human_slot if human_slot is not None else env_cfg.human_slot)
    shielded = method_spec(cfg.method).shielded if shielded is None else bool(shielded)
    if episodes < 1:
        raise ValueError(f"episodes must be >= 1, got {episodes}")
    raw = evaluate_policy(params, env_cfg, episodes, seed=FINAL_EVAL_SEED + cfg.seed if seed is None else seed,
                          shielded=shielded)
    rec = eval_record(raw)
    rec.update(method=cfg.method, scenario=env_cfg.scenario, version=version, human_slot=env_cfg.human_slot)
    return rec
