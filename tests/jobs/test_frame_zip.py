"""service/jobs/frame_zip.py: per-frame OBJ + EXR members, exact round trip."""

import io
import zipfile

import numpy as np
import pytest

from service.io.exr import read_map
from service.io.mesh import read_obj
from service.jobs.frame_zip import FrameZipWriter


def _frames(rng, start, count):
    return {"faces": np.array([[0, 1, 2], [0, 2, 3]], np.int32),
            "vertices": rng.normal(size=(count, 4, 3)).astype(np.float32),
            "displacement": rng.normal(size=(count, 8, 8)).astype(np.float32),
            "normal_map": rng.normal(size=(count, 8, 8, 3)).astype(np.float32),
            "clamped": np.full(count, 0.25, np.float32)}


def test_frames_written_in_chunks_read_back_exactly(tmp_path):
    rng = np.random.default_rng(3)
    uv = np.array([[0, 0], [1, 0], [1, 1], [0, 1]], float)
    writer = FrameZipWriter(tmp_path / "r.zip", 5, uv, np.array([[0, 1, 2], [0, 2, 3]]))
    chunks = [(0, _frames(rng, 0, 3)), (3, _frames(rng, 3, 2))]
    for start, arrays in chunks:
        writer.write(start, arrays)
    with zipfile.ZipFile(writer.finish()) as z:
        names = set(z.namelist())
        assert len(names) == 5 * 3 + 1 and "frame_0004_normal_map.exr" in names
        for start, arrays in chunks:
            for k in range(len(arrays["vertices"])):
                name = f"frame_{start + k:04d}"
                mesh = read_obj(io.BytesIO(z.read(f"{name}.obj")))
                np.testing.assert_array_equal(mesh.vertices.astype(np.float32), arrays["vertices"][k])
                np.testing.assert_array_equal(mesh.faces, arrays["faces"])
                assert mesh.uv is not None and mesh.uv.shape == (4, 2)
                np.testing.assert_array_equal(read_map(z.read(f"{name}_displacement.exr")),
                                              arrays["displacement"][k])
                np.testing.assert_array_equal(read_map(z.read(f"{name}_normal_map.exr")),
                                              arrays["normal_map"][k])
        assert z.read("clamped.csv").decode().splitlines()[1:] == [f"{i},0.25" for i in range(5)]


def test_missing_frames_are_an_error(tmp_path):
    writer = FrameZipWriter(tmp_path / "r.zip", 4)
    writer.write(0, _frames(np.random.default_rng(0), 0, 3))
    with pytest.raises(ValueError, match="got 3 of 4 frames"):
        writer.finish()


def test_the_per_frame_confidence_is_a_json_member_beside_the_frames(tmp_path):
    import json

    rng = np.random.default_rng(4)
    writer = FrameZipWriter(tmp_path / "c.zip", 3)
    conf = np.array([1.0, 0.75, 0.125], np.float32)
    writer.write(0, {**_frames(rng, 0, 2), "confidence": conf[:2]})
    writer.write(2, {**_frames(rng, 2, 1), "confidence": conf[2:]})
    with zipfile.ZipFile(writer.finish()) as z:
        assert json.loads(z.read("confidence.json")) == {"frame": [0, 1, 2], "confidence": [1.0, 0.75, 0.125]}
