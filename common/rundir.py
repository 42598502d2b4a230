"""A run directory's layout, defined once (``runs/<run_id>/``):

    config.json             resolved TrainConfig, written by ``sage train`` / ``sage up``
    supervised_config.json  the config the supervised child processes read
    metrics.jsonl, .csv     one row per learner update
    tb/                     the same rows as TensorBoard event files (with tensorboardX installed)
    metrics_discarded.jsonl rows of updates a learner restart rolled back (after its checkpoint)
    learner_version.json    the highest parameter version a learner published (versions never repeat)
    checkpoints/            atomic learner checkpoints (common/checkpoint.py)
    summary.json            final summary and deployment evaluation
    evaluated_params.npz    the tree parameters the final evaluation ran (per checkpoint version)
    status.json             the supervisor's live status snapshot
    supervisor.jsonl        the supervisor's events
    logs/<service>.log      each supervised child's stdout/stderr

plus the two ways every later reader touches them: an atomic text write and
a JSONL read that tolerates a torn last line (a killed writer).
"""
from __future__ import annotations

import json
import os
import tempfile
from dataclasses import dataclass
from pathlib import Path


@dataclass(frozen=True)
class RunDir:
    root: Path

    def __init__(self, root: str | Path):
        object.__setattr__(self, "root", Path(root))

    config = property(lambda self: self.root / "config.json")
    supervised_config = property(lambda self: self.root / "supervised_config.json")
    metrics_jsonl = property(lambda self: self.root / "metrics.jsonl")
    metrics_csv = property(lambda self: self.root / "metrics.csv")
    metrics_discarded = property(lambda self: self.root / "metrics_discarded.jsonl")
    tensorboard = property(lambda self: self.root / "tb")
    learner_version = property(lambda self: self.root / "learner_version.json")
    checkpoints = property(lambda self: self.root / "checkpoints")
    summary = property(lambda self: self.root / "summary.json")
    evaluated_params = property(lambda self: self.root / "evaluated_params.npz")
    status = property(lambda self: self.root / "status.json")
    supervisor_events = property(lambda self: self.root / "supervisor.jsonl")
    logs = property(lambda self: self.root / "logs")

    def log(self, service: str) -> Path:
        return self.logs / f"{service}.log"


def atomic_write_text(path: str | Path, text: str) -> Path:
    """Write ``text`` to ``path`` through a temporary file in the same directory
    and ``os.replace``: a reader sees the old file or the new one, never a torn one."""
    p = Path(path)
    p.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{p.name}.", suffix=".tmp", dir=p.parent)
    try:
        with os.fdopen(fd, "w") as f:
            f.write(text)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, p)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return p


def read_jsonl(path: str | Path) -> list[dict]:
    """The rows of a JSONL file; a line that does not parse (cut short by a
    killed writer) is skipped, a missing file is no rows."""
    p = Path(path)
    if not p.exists():
        return []
    rows = []
    for line in p.read_text().splitlines():
        if not line.strip():
            continue
        try:
            row = json.loads(line)
        except json.JSONDecodeError:
            continue
        if isinstance(row, dict):
            rows.append(row)
    return rows
