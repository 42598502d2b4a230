"""Reading a finished or running run directory back (``common.rundir`` names
its files): its config, its newest checkpoint and the tree parameters in it."""
from __future__ import annotations

import json
from pathlib import Path

from common.checkpoint import load_checkpoint, load_latest
from common.policy.tree_torch import policy_params_from_checkpoint
from common.rundir import RunDir, read_jsonl
from services.config import TrainConfig


def load_run(path: str | Path) -> tuple[TrainConfig, dict, int]:
    """(TrainConfig, flat tree params, checkpoint version) from a run dir or a checkpoint file."""
    p = Path(path)
    if p.is_dir():
        run = RunDir(p)
        cfg = TrainConfig.load(run.config)
        ck = load_latest(run.checkpoints)
        if ck is None:
            raise FileNotFoundError(f"{p}: no loadable checkpoint under checkpoints/")
    else:
        ck = load_checkpoint(p)
        cfg = TrainConfig.from_dict(json.loads(ck["config"]))  # the learner stores its resolved config
    return cfg, policy_params_from_checkpoint(ck), int(ck["version"])


def last_progress(run: RunDir) -> dict:
    """Updates and env steps from the learner's last metrics row (a supervised
    learner runs in another process, so its counters reach us through its log)."""
    rows = read_jsonl(run.metrics_jsonl)
    if not rows:
        return {}
    return {"updates": rows[-1].get("update"), "env_steps": rows[-1].get("env_steps")}
