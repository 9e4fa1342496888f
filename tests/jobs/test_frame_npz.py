"""service.jobs.frame_npz: chunked per-frame arrays packed into one NPZ."""

from __future__ import annotations

import numpy as np
import pytest

from service.jobs.frame_npz import FrameNpzWriter


def test_chunks_assemble_into_the_whole_arrays(tmp_path):
    rng = np.random.default_rng(0)
    vertices = rng.normal(size=(7, 5, 3)).astype(np.float32)
    maps = rng.normal(size=(7, 4, 4))
    faces = np.array([[0, 1, 2]], np.int32)
    writer = FrameNpzWriter(tmp_path, frames=7)
    for start in range(0, 7, 3):
        writer.write(start, {"vertices": vertices[start:start + 3],
                             "displacement": maps[start:start + 3], "faces": faces})
    path = writer.finish(tmp_path / "out.npz")
    with np.load(path, allow_pickle=False) as d:
        assert sorted(d.files) == ["displacement", "faces", "vertices"]
        np.testing.assert_array_equal(d["vertices"], vertices)
        np.testing.assert_array_equal(d["displacement"], maps)
        np.testing.assert_array_equal(d["faces"], faces)
        assert d["vertices"].dtype == np.float32 and d["faces"].dtype == np.int32


def test_missing_frames_are_an_error(tmp_path):
    writer = FrameNpzWriter(tmp_path, frames=4)
    writer.write(0, {"vertices": np.zeros((3, 2, 3))})
    with pytest.raises(ValueError, match="'vertices' got 3 of 4 frames"):
        writer.finish(tmp_path / "out.npz")


# -- a full disk is an OSError, never SIGBUS (issue 16, defect 2) ---------------------------
FULL_DISK_CHILD = r"""
import errno, os, sys
from pathlib import Path
import numpy as np
from service.jobs.frame_npz import FrameNpzWriter
scratch = Path(sys.argv[1])
writer = FrameNpzWriter(scratch, frames=8)
try:
    for start in range(0, 8, 2):   # 8 frames x 256 KiB = 2 MiB on a 1 MiB filesystem
        writer.write(start, {"displacement": np.ones((2, 256, 256), np.float32)})
    writer.finish()
except OSError as error:
    print("errno", errno.errorcode[error.errno], "left", sorted(os.listdir(scratch)))
    sys.exit(0)
print("no error")
sys.exit(1)
"""


def test_a_full_disk_raises_enospc_and_leaves_no_files(tmp_path):
    import subprocess
    import sys

    from tests.filesystems import small_filesystem

    with small_filesystem(1 << 20) as point:
        scratch = point / "scratch"
        scratch.mkdir()
        done = subprocess.run([sys.executable, "-c", FULL_DISK_CHILD, str(scratch)],
                              capture_output=True, text=True, timeout=60)
        assert done.returncode == 0, (done.returncode, done.stdout, done.stderr[-2000:])
        assert done.stdout.split() == ["errno", "ENOSPC", "left", "[]"]


def test_result_npz_on_a_full_disk_is_removed(tmp_path):
    from tests.filesystems import small_filesystem

    with small_filesystem(3 << 19) as point:     # 1.5 MiB: the frames fit, the npz does not
        writer = FrameNpzWriter(point, frames=4)
        writer.write(0, {"vertices": np.ones((4, 256, 256), np.float32)})   # 1 MiB
        with pytest.raises(OSError) as raised:
            writer.finish(point / "result.npz")
        assert raised.value.errno == 28
        assert sorted(p.name for p in point.iterdir()) == []
