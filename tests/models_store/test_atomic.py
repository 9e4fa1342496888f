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


def test_sha256_file_mapped_or_read_is_hashlib_of_the_bytes(tmp_path):
    """The mapped path (regular files), an empty file (cannot be mapped) and a pipe (read in
    chunks) all give hashlib's digest of the content."""
    import hashlib
    import threading

    data = np.random.default_rng(0).bytes(3 << 20)
    path = tmp_path / "blob.bin"
    path.write_bytes(data)
    assert sha256_file(path) == hashlib.sha256(data).hexdigest()
    (tmp_path / "empty").write_bytes(b"")
    assert sha256_file(tmp_path / "empty") == hashlib.sha256(b"").hexdigest()
    fifo = tmp_path / "fifo"
    os.mkfifo(fifo)
    writer = threading.Thread(target=lambda: fifo.write_bytes(data[:100_000]))
    writer.start()
    assert sha256_file(fifo, chunk=4096) == hashlib.sha256(data[:100_000]).hexdigest()
    writer.join(5)
