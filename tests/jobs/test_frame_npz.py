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
