"""Tests for models_store.atomic: all-or-nothing writes with the usual file mode."""

import os
import stat

import numpy as np
import pytest

from models_store.atomic import atomic_open, sha256_file, write_bytes, write_npz


def test_written_files_get_the_mode_open_would_give(tmp_path):
    path = tmp_path / "a" / "b.bin"
    digest = write_bytes(path, b"facesynth")
    mask = os.umask(0o022)
    os.umask(mask)
    assert stat.S_IMODE(path.stat().st_mode) == 0o666 & ~mask
    assert digest == sha256_file(path)
    assert write_npz(tmp_path / "x.npz", {"a": np.arange(3)}) == sha256_file(tmp_path / "x.npz")


def test_a_failed_write_leaves_the_old_file_and_no_temporary(tmp_path):
    path = tmp_path / "c.bin"
    write_bytes(path, b"old")
    with pytest.raises(RuntimeError):
        with atomic_open(path) as f:
            f.write(b"half")
            raise RuntimeError("crash")
    assert path.read_bytes() == b"old"
    assert [p.name for p in tmp_path.iterdir()] == ["c.bin"]
