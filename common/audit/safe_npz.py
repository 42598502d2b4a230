"""Loading a user's .npz as data within a size budget.

``np.load`` allocates what an array's npy header declares before it reads a
byte: a 100-byte file whose header claims 2**40 elements asks for terabytes.
``load_npz`` reads every member's header first (``numpy.lib.format``), and
refuses, naming the member, one whose declared size exceeds what the archive
says it holds uncompressed, or object arrays, or a total past ``max_bytes``;
only then does it load the arrays (never with pickle).
"""
from __future__ import annotations

import math
import zipfile
from pathlib import Path

import numpy as np
from numpy.lib import format as npy_format


def _declared_bytes(z: zipfile.ZipFile, info: zipfile.ZipInfo) -> int:
    with z.open(info) as f:
        version = npy_format.read_magic(f)
        if version == (1, 0):
            shape, _, dtype = npy_format.read_array_header_1_0(f)
        elif version == (2, 0):
            shape, _, dtype = npy_format.read_array_header_2_0(f)
        else:
            raise ValueError(f"npy format version {version} not supported")
    if dtype.hasobject:
        raise ValueError("object array (pickled data is never loaded)")
    return math.prod(shape) * dtype.itemsize


def load_npz(path: str | Path, max_bytes: int) -> dict[str, np.ndarray]:
    """Every array of the .npz at ``path`` (a ``ValueError`` naming the member for a
    header that claims more than the file holds or the budget allows)."""
    path = Path(path)
    total = 0
    with zipfile.ZipFile(path) as z:
        for info in z.infolist():
            name = info.filename
            try:
                n = _declared_bytes(z, info)
            except ValueError as exc:
                raise ValueError(f"{path}: member {name}: {exc}") from None
            if n > info.file_size:
                raise ValueError(f"{path}: member {name} declares {n} bytes of data but holds {info.file_size}")
            total += n
            if total > max_bytes:
                raise ValueError(f"{path}: arrays of more than {max_bytes} bytes (the size budget); not loaded")
    with np.load(path, allow_pickle=False) as data:
        return {k: data[k] for k in data.files}
