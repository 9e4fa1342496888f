"""service/jobs/frame_usd.py: chunks in, one USD point cache (or a zip with its maps) out,
read back with pxr exactly."""

import zipfile

import numpy as np
import pytest
from pxr import Usd, UsdGeom, UsdShade

from service.io.exr import read_map
from service.jobs.frame_usd import FrameUsdWriter
from service.jobs.formats import artifact_type, check_result_format, usd_is_zip
from service.methods.inputs import InvalidInput

FACES = np.array([[0, 1, 2], [0, 2, 3]], np.int32)
UV = np.array([[0, 0], [1, 0], [1, 1], [0, 1]], float)


def _frames(rng, count, maps=False):
    arrays = {"faces": FACES, "vertices": rng.normal(size=(count, 4, 3)).astype(np.float32),
              "clamped": np.full(count, 0.5, np.float32)}
    if maps:
        arrays["displacement"] = rng.normal(size=(count, 8, 8)).astype(np.float32)
        arrays["albedo"] = rng.uniform(size=(count, 8, 8, 3)).astype(np.float32)
    return arrays


def _points(stage):
    mesh = UsdGeom.Mesh(stage.GetPrimAtPath("/Face/Mesh"))
    times = mesh.GetPointsAttr().GetTimeSamples()
    return mesh, times, np.stack([np.asarray(mesh.GetPointsAttr().Get(t)) for t in times])


def test_chunks_become_one_cache_of_float32_points(tmp_path):
    rng = np.random.default_rng(5)
    chunks = [(0, _frames(rng, 3)), (3, _frames(rng, 2))]
    writer = FrameUsdWriter(tmp_path, 5, UV, None, fps=24.0)
    for start, arrays in chunks:
        writer.write(start, arrays)
    path = writer.finish()
    assert path.suffix == ".usd"
    stage = Usd.Stage.Open(str(path))
    mesh, times, points = _points(stage)
    assert times == [0.0, 1.0, 2.0, 3.0, 4.0] and stage.GetTimeCodesPerSecond() == 24.0
    assert points.dtype == np.float32
    np.testing.assert_array_equal(points, np.concatenate([a["vertices"] for _, a in chunks]))
    assert list(mesh.GetFaceVertexCountsAttr().Get()) == [3, 3]
    assert list(mesh.GetFaceVertexIndicesAttr().Get()) == FACES.ravel().tolist()
    assert UsdGeom.GetStageMetersPerUnit(stage) == 0.001


def test_maps_go_into_a_zip_beside_the_cache_that_references_them(tmp_path):
    rng = np.random.default_rng(6)
    arrays = _frames(rng, 2, maps=True)
    writer = FrameUsdWriter(tmp_path, 2, UV, FACES, as_zip=True)
    writer.write(0, arrays)
    archive = writer.finish()
    with zipfile.ZipFile(archive) as z:
        assert sorted(z.namelist()) == ["clamped.csv", "frame_0000_albedo.exr",
                                        "frame_0000_displacement.exr", "frame_0001_albedo.exr",
                                        "frame_0001_displacement.exr", "performance.usd"]
        z.extractall(tmp_path / "out")
        np.testing.assert_array_equal(read_map(z.read("frame_0001_displacement.exr")),
                                      arrays["displacement"][1])
    stage = Usd.Stage.Open(str(tmp_path / "out" / "performance.usd"))
    _, _, points = _points(stage)
    np.testing.assert_array_equal(points, arrays["vertices"])
    shader = UsdShade.Shader(stage.GetPrimAtPath("/Face/Looks/Material/displacementTexture"))
    file = shader.GetInput("file").GetAttr()
    assert [file.Get(t).path for t in (0, 1)] == ["./frame_0000_displacement.exr",
                                                  "./frame_0001_displacement.exr"]
    resolved = file.Get(1).resolvedPath
    np.testing.assert_array_equal(read_map(open(resolved, "rb").read()), arrays["displacement"][1])
    albedo = UsdShade.Shader(stage.GetPrimAtPath("/Face/Looks/Material/diffuseColorTexture"))
    assert albedo.GetInput("file").GetAttr().Get(0).path == "./frame_0000_albedo.exr"


def test_missing_frames_and_missing_meshes_are_errors(tmp_path):
    writer = FrameUsdWriter(tmp_path, 4, UV)
    writer.write(0, _frames(np.random.default_rng(0), 3))
    with pytest.raises(ValueError, match="got 3 of 4 frames"):
        writer.finish()
    writer = FrameUsdWriter(tmp_path, 1, UV)
    writer.write(0, {"clamped": np.zeros(1)})
    with pytest.raises(ValueError, match="needs a mesh output"):
        writer.finish()


def test_the_usd_artifact_is_a_file_or_a_zip_by_the_outputs():
    assert not usd_is_zip(["mesh"]) and not usd_is_zip(["mesh_detailed"])
    assert usd_is_zip(["mesh", "displacement"]) and usd_is_zip(["mesh", "mesh_detailed"])
    assert artifact_type("usd", ["mesh"]) == ("application/octet-stream", "usd")
    assert artifact_type("usd", ["mesh", "albedo"]) == ("application/zip", "zip")
    assert artifact_type("npz", ["mesh", "albedo"]) == ("application/x-npz", "npz")
    with pytest.raises(InvalidInput, match="needs a mesh output: add 'mesh'"):
        check_result_format("usd", ["displacement"])
    with pytest.raises(InvalidInput, match="'fbx' is not supported"):
        check_result_format("fbx", ["mesh"])
