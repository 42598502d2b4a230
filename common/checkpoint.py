"""Atomic learner checkpoints, loadable with ``torch.load(weights_only=True)``.

A checkpoint is written to a temporary file in the same directory, flushed
and fsync'ed, then ``os.replace``'d onto ``ckpt_<version>.pt`` (atomic on
POSIX), and the directory is fsync'ed so the rename survives a crash. A
reader therefore sees either the old set of checkpoints or the new one, never
a torn file. Contents must be weights-only-safe: tensors, numbers, strings,
lists, dicts (the config goes in as a JSON string, RNG states as tensors or
plain containers).

The directory's ``manifest.json`` (written atomically after each checkpoint)
lists the checkpoints this run wrote, with their versions, sizes and SHA-256
content hashes. Only those count: rotation keeps the newest ``keep`` of them
and never touches another file (junk named ``ckpt_99999999.pt`` can no longer
push the real ones out), and ``load_latest`` loads the newest whose bytes
match the manifest and whose payload is a checkpoint of that version, falling
back to older ones with a logged warning. A directory with checkpoints of
which none loads raises ``CheckpointError``: the learner must stop, never
silently start over from update 0. A directory without a manifest (written
before it existed) is read file by file, newest first, the same way.
"""
from __future__ import annotations

import hashlib
import io
import json
import logging
import os
import re
import tempfile
from pathlib import Path

log = logging.getLogger(__name__)

_NAME = re.compile(r"^ckpt_(\d{8,})\.pt$")
MANIFEST = "manifest.json"


class CheckpointError(RuntimeError):
    """Checkpoints exist but none of them loads as this run's checkpoint;
    ``failures``: one "<file>: <why>" per checkpoint, newest first."""

    def __init__(self, message: str, failures: list[str]):
        super().__init__(message)
        self.failures = failures


def checkpoint_path(directory: str | Path, version: int) -> Path:
    return Path(directory) / f"ckpt_{int(version):08d}.pt"


def _atomic_write(d: Path, final: Path, data: bytes, prefix: str) -> None:
    fd, tmp = tempfile.mkstemp(prefix=prefix, suffix=".tmp", dir=d)
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(data)
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


def save_checkpoint(directory: str | Path, version: int, payload: dict, keep: int = 3) -> Path:
    """Atomically write ``payload`` as the checkpoint of ``version``, record it in
    the manifest, and keep the newest ``keep`` of the manifest's checkpoints."""
    d = Path(directory)
    d.mkdir(parents=True, exist_ok=True)
    final = checkpoint_path(d, version)
    import torch   # here, not at import: services import CheckpointError without torch's ~200 MB

    buf = io.BytesIO()
    torch.save(payload, buf)
    data = buf.getvalue()
    _atomic_write(d, final, data, ".ckpt_")
    entries = [e for e in (read_manifest(d) or []) if e["name"] != final.name]
    entries.append({"name": final.name, "version": int(version), "bytes": len(data),
                    "sha256": hashlib.sha256(data).hexdigest()})
    entries.sort(key=lambda e: e["version"])
    drop = entries[:-keep] if keep > 0 else []
    kept = entries[len(drop):]
    # the manifest first: a crash between the two leaves an unlisted file, never a listed hole
    _atomic_write(d, d / MANIFEST, (json.dumps({"checkpoints": kept}, indent=1) + "\n").encode(), ".manifest_")
    for e in drop:
        (d / e["name"]).unlink(missing_ok=True)
    return final


def read_manifest(directory: str | Path) -> list[dict] | None:
    """The manifest's entries, oldest first; None without a readable manifest."""
    p = Path(directory) / MANIFEST
    try:
        raw = json.loads(p.read_text())
        entries = [{"name": str(e["name"]), "version": int(e["version"]), "bytes": int(e["bytes"]),
                    "sha256": str(e["sha256"])} for e in raw["checkpoints"]]
    except FileNotFoundError:
        return None
    except (ValueError, KeyError, TypeError, OSError) as exc:
        log.warning("%s is not a checkpoint manifest (%s); reading the checkpoint files themselves", p, exc)
        return None
    return [e for e in entries if _NAME.match(e["name"])]


def list_checkpoints(directory: str | Path) -> list[Path]:
    """This run's checkpoint files, oldest first: the manifest's, or (no manifest)
    every ``ckpt_<version>.pt`` file (temporary files are ignored)."""
    d = Path(directory)
    if not d.is_dir():
        return []
    entries = read_manifest(d)
    if entries is not None:
        return [d / e["name"] for e in entries]
    found = [(int(m.group(1)), p) for p in d.iterdir() if (m := _NAME.match(p.name))]
    return [p for _, p in sorted(found)]


def load_checkpoint(path: str | Path) -> dict:
    import torch

    return torch.load(path, map_location="cpu", weights_only=True)


def _load_checked(path: Path, entry: dict | None) -> dict:
    data = path.read_bytes()
    if entry is not None:
        if len(data) != entry["bytes"] or hashlib.sha256(data).hexdigest() != entry["sha256"]:
            raise ValueError("content does not match the manifest's hash")
    import torch

    ck = torch.load(io.BytesIO(data), map_location="cpu", weights_only=True)
    m = _NAME.match(path.name)
    if not isinstance(ck, dict) or "version" not in ck or int(ck["version"]) != int(m.group(1)):
        raise ValueError("not a learner checkpoint of the version its name says")
    return ck


def load_newest(directory: str | Path, n: int) -> list[dict]:
    """The newest ``n`` of this run's checkpoints that load and match the manifest, oldest
    first (a damaged one is skipped with a logged warning): what a final evaluation over
    the last checkpoints runs."""
    d = Path(directory)
    entries = read_manifest(d) if d.is_dir() else None
    candidates = ([(d / e["name"], e) for e in entries] if entries is not None
                  else [(p, None) for p in list_checkpoints(d)])
    out = []
    for path, entry in reversed(candidates):
        try:
            out.append(_load_checked(path, entry))
        except Exception as exc:  # noqa: BLE001 - skipped, as resume skips it
            log.warning("checkpoint %s does not load (%s); not evaluated", path, str(exc).splitlines()[0][:160]
                        if str(exc) else type(exc).__name__)
            continue
        if len(out) == n:
            break
    return out[::-1]


def load_latest(directory: str | Path) -> dict | None:
    """Newest of this run's checkpoints that loads, or None when there is none.
    A damaged one is skipped with a logged warning in favour of the previous;
    raises ``CheckpointError`` when there are checkpoints and none loads."""
    d = Path(directory)
    if not d.is_dir():
        return None
    entries = read_manifest(d)
    candidates = ([(d / e["name"], e) for e in entries] if entries is not None
                  else [(p, None) for p in list_checkpoints(d)])
    failures = []
    for path, entry in reversed(candidates):
        try:
            ck = _load_checked(path, entry)
        except Exception as exc:  # noqa: BLE001 - fall back to an older checkpoint
            why = str(exc).splitlines()[0][:160] if str(exc) else type(exc).__name__
            failures.append(f"{path.name}: {why}")
            log.warning("checkpoint %s does not load (%s); falling back to the one before", path, why)
            continue
        if failures:
            log.warning("resuming from %s, the newest checkpoint that loads (%d newer skipped)", path.name,
                        len(failures))
        return ck
    if failures:
        raise CheckpointError(f"{d}: none of its {len(failures)} checkpoint(s) loads (newest: {failures[0]}); "
                              "refusing to start over from update 0: restore a checkpoint there or use a "
                              "new run directory", failures)
    return None
