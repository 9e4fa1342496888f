"""Small and read-only filesystems for fault tests, made and removed by the test.

:func:`small_filesystem` mounts a size-limited tmpfs on a fresh temporary directory (as
root; the machines the tests run on run them as root), yields the mount point and unmounts
and removes it afterwards, whatever happened. Where mounting is impossible (not root, no
``mount``, a container without ``CAP_SYS_ADMIN``) the test is skipped with the reason.
:func:`read_only` remounts such a filesystem read-only for the duration of a block.

Only filesystems these helpers created are ever mounted, remounted or unmounted.
"""

from __future__ import annotations

import contextlib
import os
import shutil
import subprocess
import tempfile
from pathlib import Path
from typing import Iterator

import pytest


def _run(*argv: str) -> subprocess.CompletedProcess:
    return subprocess.run(argv, capture_output=True, text=True, timeout=30)


@contextlib.contextmanager
def small_filesystem(size_bytes: int, prefix: str = "facesynth-smallfs-") -> Iterator[Path]:
    """A tmpfs of ``size_bytes`` mounted on a new temporary directory (skips if impossible)."""
    if os.geteuid() != 0 or shutil.which("mount") is None:
        pytest.skip("mounting a size-limited tmpfs needs root and mount(8)")
    point = Path(tempfile.mkdtemp(prefix=prefix))
    done = _run("mount", "-t", "tmpfs", "-o", f"size={int(size_bytes)},mode=0755",
                "facesynth-test", str(point))
    if done.returncode != 0:
        point.rmdir()
        pytest.skip(f"cannot mount a tmpfs here: {done.stderr.strip()}")
    try:
        yield point
    finally:
        _run("umount", "-l", str(point))
        with contextlib.suppress(OSError):
            point.rmdir()


@contextlib.contextmanager
def read_only(point: Path) -> Iterator[Path]:
    """Remount the filesystem :func:`small_filesystem` made at ``point`` read-only."""
    done = _run("mount", "-o", "remount,ro", str(point))
    if done.returncode != 0:
        pytest.skip(f"cannot remount {point} read-only: {done.stderr.strip()}")
    try:
        yield point
    finally:
        _run("mount", "-o", "remount,rw", str(point))


def fill(point: Path, leave_bytes: int = 0) -> Path:
    """Fill the filesystem at ``point`` up to ``leave_bytes`` free; returns the filler file
    (delete it to free the space again)."""
    filler = point / "filler"
    free = shutil.disk_usage(point).free - int(leave_bytes)
    with open(filler, "wb") as f:
        chunk = b"\0" * (1 << 16)
        try:
            while free > 0:
                free -= f.write(chunk[:min(len(chunk), free)])
        except OSError:
            pass
    return filler
