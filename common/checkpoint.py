"""Atomic learner checkpoints, loadable with ``torch.load(weights_only=True)``.

A checkpoint is written to a temporary file in the same directory, flushed
and fsync'ed, then ``os.replace``'d onto ``ckpt_<version>.pt`` (atomic on
POSIX), and the directory is fsync'ed so the rename survives a crash. A
reader therefore sees either the old set of checkpoints or the new one, never
a torn file. Contents must be weights-only-safe: tensors, numbers, strings,
lists, dicts (the config goes in as a JSON string, RNG states as tensors or
plain containers).
"""
from __future__ import annotations

import os
import re
import tempfile
from pathlib import Path

import torch

_NAME = re.compile(r"^ckpt_(\d{8,})\.pt$")


def checkpoint_path(directory: str | Path, version: int) -> Path:
    return Path(directory) / f"ckpt_{int(version):08d}.pt"


def save_checkpoint(directory: str | Path, version: int, payload: dict, keep: int = 3) -> Path:
    """Atomically write ``payload`` as the checkpoint of ``version``; keep the
    newest ``keep`` checkpoints."""
    d = Path(directory)
    d.mkdir(parents=True, exist_ok=True)
    final = checkpoint_path(d, version)
    fd, tmp = tempfile.mkstemp(prefix=".ckpt_", suffix=".tmp", dir=d)
    try:
        with os.fdopen(fd, "wb") as f:
            torch.save(payload, f)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, final)
    except BaseException:
        try:
            os.unlink(tmp)
        except FileNotFoundError:
            pass
        raise
    dfd = os.open(d, os.O_RDONLY)
    try:
        os.fsync(dfd)
    finally:
        os.close(dfd)
    if keep > 0:
        for old in list_checkpoints(d)[:-keep]:
            old.unlink(missing_ok=True)
    return final


def list_checkpoints(directory: str | Path) -> list[Path]:
    """Checkpoint files, oldest first (temporary files are ignored)."""
    d = Path(directory)
    if not d.is_dir():
        return []
    found = [(int(m.group(1)), p) for p in d.iterdir() if (m := _NAME.match(p.name))]
    return [p for _, p in sorted(found)]


def load_checkpoint(path: str | Path) -> dict:
    return torch.load(path, map_location="cpu", weights_only=True)


def load_latest(directory: str | Path) -> dict | None:
    """Newest checkpoint that loads, or None. A file that fails to load (e.g.
    a disk error after the rename) is skipped in favour of the previous one."""
    for p in reversed(list_checkpoints(directory)):
        try:
            return load_checkpoint(p)
        except Exception:  # noqa: BLE001 - fall back to an older checkpoint
            continue
    return None
