"""Atomic file writes: write to a temporary sibling, fsync, rename.

A reader never sees a half-written file, and a crash leaves either the old file or the
new one, never a mix.
"""

from __future__ import annotations

import hashlib
import os
import tempfile
from contextlib import contextmanager
from pathlib import Path
from typing import Iterator, BinaryIO

import numpy as np


@contextmanager
def atomic_open(path: str | Path) -> Iterator[BinaryIO]:
    """Open ``path`` for binary writing; the file appears only when the block succeeds."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        # mkstemp creates 0600; give the file the mode open() would (0666 minus the umask)
        os.fchmod(fd, 0o666 & ~_UMASK)
        with os.fdopen(fd, "wb") as f:
            yield f
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def _umask() -> int:
    """The process umask (read once, at import: reading it means setting and restoring it)."""
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


_UMASK = _umask()


def write_bytes(path: str | Path, data: bytes) -> str:
    """Write ``data`` atomically; return its sha256 hex digest."""
    with atomic_open(path) as f:
        f.write(data)
    return hashlib.sha256(data).hexdigest()


def write_npz(path: str | Path, arrays: dict[str, np.ndarray]) -> str:
    """Write arrays as an uncompressed .npz atomically; return the file's sha256."""
    with atomic_open(path) as f:
        np.savez(f, **arrays)
    return sha256_file(path)


def sha256_file(path: str | Path, chunk: int = 1 << 20) -> str:
    """sha256 hex digest of a file, read in chunks."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        while block := f.read(chunk):
            h.update(block)
    return h.hexdigest()
