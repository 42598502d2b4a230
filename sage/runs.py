"""Reading a finished or running run directory back (``common.rundir`` names
its files): its config, its newest checkpoint and the tree parameters in it."""
from __future__ import annotations

import json
import pickle
import zipfile
from pathlib import Path

from common.checkpoint import CheckpointError, list_checkpoints, load_checkpoint, load_latest
from common.policy.tree_torch import policy_params_from_checkpoint
from common.rundir import RunDir, read_jsonl
from sage.errors import load_error, one_line
from services.config import TrainConfig

# What torch.load raises on a corrupt, truncated or foreign file (weights_only=True).
CHECKPOINT_LOAD_ERRORS = (pickle.UnpicklingError, EOFError, RuntimeError, zipfile.BadZipFile, ValueError,
                          AttributeError, IndexError)


def read_config(path: str | Path) -> TrainConfig:
    """``TrainConfig.load``: a ``FileNotFoundError`` or ``ValueError``/``TypeError`` for bad input
    (not a JSON object, NaN/Infinity, nested too deeply, a field out of its type or range)."""
    return TrainConfig.load(path)


def read_checkpoint(path: str | Path) -> dict:
    """``common.checkpoint.load_checkpoint``; a file that is missing is a ``FileNotFoundError``,
    one that does not load (corrupt, truncated, not a checkpoint) a ``ValueError`` naming it."""
    p = Path(path)
    if not p.exists():
        raise FileNotFoundError(2, "No such file or directory", str(p))
    if p.is_dir():
        raise IsADirectoryError(21, "Is a directory", str(p))
    try:
        ck = load_checkpoint(p)
    except CHECKPOINT_LOAD_ERRORS as exc:
        raise load_error(p, "checkpoint", exc) from exc
    if not isinstance(ck, dict):
        raise ValueError(f"{p}: not a learner checkpoint (holds a {type(ck).__name__})")
    return ck


def load_run(path: str | Path) -> tuple[TrainConfig, dict, int]:
    """(TrainConfig, flat tree params, checkpoint version) from a run dir or a checkpoint file.

    Bad input raises ``FileNotFoundError`` (no such path, no checkpoint) or
    ``ValueError`` naming the file (corrupt config.json or checkpoint)."""
    p = Path(path)
    if p.is_dir():
        run = RunDir(p)
        if not run.config.exists():
            raise FileNotFoundError(f"{p}: not a run directory (no config.json)")
        try:
            cfg = read_config(run.config)
        except (ValueError, TypeError) as exc:
            raise ValueError(f"{run.config}: not a valid run config ({one_line(exc)})") from exc
        try:
            ck = load_latest(run.checkpoints)
        except CheckpointError as exc:
            raise ValueError(f"{p}: no loadable checkpoint under checkpoints/ ({len(exc.failures)} there, "
                             f"none loads; newest {exc.failures[0]})") from None
        if ck is None:
            found = len(list_checkpoints(run.checkpoints))
            raise FileNotFoundError(f"{p}: no loadable checkpoint under checkpoints/"
                                    + (f" ({found} file(s) there, none loads)" if found else ""))
        source = run.checkpoints
    else:
        ck = read_checkpoint(p)
        source = p
        try:
            cfg = TrainConfig.from_dict(json.loads(ck["config"]))  # the learner stores its resolved config
        except (KeyError, TypeError, ValueError) as exc:
            raise ValueError(f"{p}: not a learner checkpoint (no valid run config in it: {one_line(exc)})") from exc
    try:
        return cfg, policy_params_from_checkpoint(ck), int(ck["version"])
    except (KeyError, TypeError, ValueError) as exc:
        raise ValueError(f"{source}: not a learner checkpoint ({one_line(exc)})") from exc


def last_progress(run: RunDir) -> dict:
    """Updates and env steps from the learner's last metrics row (a supervised
    learner runs in another process, so its counters reach us through its log)."""
    rows = read_jsonl(run.metrics_jsonl)
    if not rows:
        return {}
    return {"updates": rows[-1].get("update"), "env_steps": rows[-1].get("env_steps")}
