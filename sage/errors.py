"""Expected user errors of the ``sage`` CLI: one line on stderr, exit code 2.

A command handler checks what the user gave it (flags, files) before any real
work, inside ``with user_input():``. The exceptions that validation and file
loading raise there (``ValueError`` from the config dataclasses, ``OSError``
for a missing or unreadable file, ``json.JSONDecodeError``, a corrupt
checkpoint or archive) become a ``UsageError``, which ``sage.cli.main`` prints
as ``sage <command>: <message>`` and turns into exit code 2. Anything raised
outside such a block (a bug in training, evaluation, ...) keeps its traceback.
Set ``SAGE_TRACEBACK=1`` to see the traceback of a usage error too.

The argparse ``type=`` helpers below make argparse itself reject an
out-of-range number (argparse exits 2 with its usage line).
"""
from __future__ import annotations

import argparse
import contextlib
import math
import pickle
import zipfile
from pathlib import Path

# What loading or validating user-given input raises for bad input. Kept to
# these: an unexpected exception type in an input block is a bug and keeps
# its traceback.
INPUT_ERRORS = (ValueError, TypeError, KeyError, OSError, EOFError, pickle.UnpicklingError, zipfile.BadZipFile)


class UsageError(Exception):
    """Bad user input: ``sage <command>: <message>``, exit code 2."""


def one_line(exc: BaseException) -> str:
    """A short one-line description of ``exc`` (its message's first line)."""
    if isinstance(exc, FileNotFoundError) and exc.filename is not None:
        return f"no such file or directory: {exc.filename}"
    if isinstance(exc, OSError) and exc.strerror and exc.filename is not None:
        return f"{exc.strerror.lower()}: {exc.filename}"
    if isinstance(exc, KeyError):
        return f"missing key {exc.args[0]!r}" if exc.args else "missing key"
    lines = [ln.strip() for ln in str(exc).splitlines() if ln.strip()]
    text = lines[0] if lines else type(exc).__name__
    return text if len(text) <= 400 else text[:397] + "..."


@contextlib.contextmanager
def user_input(context: str | None = None):
    """Turn the input errors raised inside the block into a ``UsageError``
    (prefixed by ``context``, e.g. the file being read)."""
    try:
        yield
    except UsageError:
        raise
    except INPUT_ERRORS as exc:
        msg = one_line(exc)
        if context and context not in msg:
            msg = f"{context}: {msg}"
        raise UsageError(msg) from exc


def load_error(path: str | Path, what: str, exc: BaseException) -> ValueError:
    """A ``ValueError`` naming ``path`` for a file that failed to load (corrupt,
    truncated, not the expected kind)."""
    detail = one_line(exc)
    if isinstance(exc, EOFError) and detail == type(exc).__name__:
        detail = "empty or truncated file"
    if isinstance(exc, pickle.UnpicklingError) and detail.startswith("Weights only load failed"):
        detail = "not a torch weights-only file"  # torch's long advice does not apply to a corrupt file
    if len(detail) > 160:
        detail = detail[:157] + "..."
    return ValueError(f"{path}: not a readable {what} ({type(exc).__name__}: {detail})")


# ----------------------------------------------------------------- argparse types
def _number(kind, test, wanted: str):
    def parse(text: str):
        try:
            value = kind(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected {wanted}, got {text!r}") from None
        if kind is float and math.isnan(value):
            raise argparse.ArgumentTypeError(f"expected {wanted}, got {text!r}")
        if not test(value):
            raise argparse.ArgumentTypeError(f"expected {wanted}, got {text}")
        return value

    parse.__name__ = wanted.replace(" ", "_")  # argparse names the type in some messages
    return parse


positive_int = _number(int, lambda v: v >= 1, "an integer >= 1")
nonneg_int = _number(int, lambda v: v >= 0, "an integer >= 0")
positive_float = _number(float, lambda v: 0 < v < float("inf"), "a number > 0")
nonneg_float = _number(float, lambda v: 0 <= v < float("inf"), "a number >= 0")
port = _number(int, lambda v: 0 <= v <= 65535, "a port 0..65535 (0 = off)")


def int_list(text: str, minimum: int | None = None, name: str = "list") -> list[int]:
    """``"0,1,2"`` -> ``[0, 1, 2]``; a ``ValueError`` naming the bad item."""
    out = []
    for part in (p.strip() for p in text.split(",")):
        if not part:
            continue
        try:
            value = int(part)
        except ValueError:
            raise ValueError(f"{name}: {part!r} is not an integer (expected e.g. 0,1,2)") from None
        if minimum is not None and value < minimum:
            raise ValueError(f"{name}: {value} must be >= {minimum}")
        out.append(value)
    if not out:
        raise ValueError(f"{name}: empty list {text!r}")
    return out


# ----------------------------------------------------------------- output paths
def output_file(path: str | Path, flag: str, figure: bool = False) -> Path:
    """A file the command will write: not a directory, its folder created; for a
    figure, a suffix matplotlib knows. A ``UsageError`` naming ``flag`` otherwise."""
    p = Path(path)
    if figure:
        from matplotlib.backend_bases import FigureCanvasBase  # matplotlib only where a figure is drawn

        formats = FigureCanvasBase.get_supported_filetypes()
        suffix = p.suffix.lower().lstrip(".")
        if suffix and suffix not in formats:
            raise UsageError(f"{flag} {p}: unknown figure format {suffix!r}; use one of {', '.join(sorted(formats))}")
    if p.is_symlink():   # writing would overwrite whatever the link points to
        raise UsageError(f"{flag} {p} is a symbolic link; give a plain file name (remove the link first)")
    if p.is_dir():
        raise UsageError(f"{flag} {p} is a directory; give a file name")
    for parent in p.parents:
        if parent.exists():
            if not parent.is_dir():
                raise UsageError(f"{flag} {p}: {parent} is not a directory")
            break
    with user_input(f"{flag} {p}"):
        p.parent.mkdir(parents=True, exist_ok=True)
    return p


def output_dir(path: str | Path, flag: str, files: tuple[str, ...] = ()) -> Path:
    """A directory the command will write into (created); a ``UsageError`` if it is a
    file, or if one of the ``files`` it will write there is a symbolic link (writing
    would overwrite the link's target)."""
    p = Path(path)
    if p.exists() and not p.is_dir():
        raise UsageError(f"{flag} {p} exists and is not a directory")
    links = [name for name in files if (p / name).is_symlink()]
    if links:
        raise UsageError(f"{flag} {p}: {', '.join(links)} is a symbolic link; remove it or choose another directory")
    with user_input(f"{flag} {p}"):
        p.mkdir(parents=True, exist_ok=True)
    return p
