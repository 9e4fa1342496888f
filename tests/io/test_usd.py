"""USD point cache: read back with pxr, points bit-exact as float32, topology and UVs kept."""

import os

import numpy as np
import pytest
from pxr import Usd, UsdGeom, UsdShade

from service.io.triangle_mesh import NO_UV, Mesh
from service.io.usd import write_usd_cache

# a quad split in two, and a triangle; per-corner uv with a seam at vertex 0
VERTICES = np.array([[0, 0, 0], [10, 0, 0], [10, 10, 0], [0, 10, 0], [-10, 5, 0]], float)
FACES = np.array([[0, 1, 2], [0, 2, 3], [0, 3, 4]])
UV = np.array([[0, 0], [1, 0], [1, 1], [0, 1], [0.5, 0.5], [0.25, 0.75]])
UV_FACES = np.array([[0, 1, 2], [0, 2, 3], [5, 3, 4]])


def _mesh(per_corner=True):
    if per_corner:
        return Mesh(VERTICES, FACES, UV, UV_FACES, quad_split=np.array([0, 0, 1]))
    return Mesh(VERTICES, FACES, UV[:5], quad_split=np.array([0, 0, 1]))


def _frames(count=4, seed=0):
    """(F,V,3) positions with float32-awkward values (not representable exactly in float64 text)."""
    rng = np.random.default_rng(seed)
    return VERTICES[None] + rng.normal(scale=3.0, size=(count, len(VERTICES), 3)) * np.pi


@pytest.mark.parametrize("suffix", [".usd", ".usda", ".usdc"])
def test_points_read_back_bit_exact_as_float32_at_every_time_code(suffix, tmp_path):
    frames = _frames()
    write_usd_cache(tmp_path / f"perf{suffix}", _mesh(), frames, fps=24.0, start_frame=10)
    stage = Usd.Stage.Open(str(tmp_path / f"perf{suffix}"))
    mesh = UsdGeom.Mesh(stage.GetPrimAtPath("/Face/Mesh"))
    assert mesh.GetPointsAttr().GetTimeSamples() == [10.0, 11.0, 12.0, 13.0]
    for f, expected in enumerate(frames.astype(np.float32)):
        back = np.asarray(mesh.GetPointsAttr().Get(10 + f), dtype=np.float32)
        assert back.dtype == np.float32 and np.array_equal(back.view(np.uint32), expected.view(np.uint32))
        extent = np.asarray(mesh.GetExtentAttr().Get(10 + f))
        assert np.array_equal(extent, [expected.min(axis=0), expected.max(axis=0)])
    assert (stage.GetStartTimeCode(), stage.GetEndTimeCode()) == (10.0, 13.0)


def test_topology_is_the_file_polygons_written_once(tmp_path):
    write_usd_cache(tmp_path / "perf.usd", _mesh(), _frames(), fps=30.0)
    stage = Usd.Stage.Open(str(tmp_path / "perf.usd"))  # the prims live as long as the stage
    mesh = UsdGeom.Mesh(stage.GetPrimAtPath("/Face/Mesh"))
    sizes, corners, _ = _mesh().polygons()
    assert list(mesh.GetFaceVertexCountsAttr().Get()) == sizes.tolist() == [4, 3]
    assert list(mesh.GetFaceVertexIndicesAttr().Get()) == corners.tolist() == [0, 1, 2, 3, 0, 3, 4]
    assert mesh.GetFaceVertexIndicesAttr().GetNumTimeSamples() == 0
    assert mesh.GetSubdivisionSchemeAttr().Get() == UsdGeom.Tokens.none


def test_per_corner_uv_is_an_indexed_face_varying_st_primvar(tmp_path):
    write_usd_cache(tmp_path / "perf.usd", _mesh(), _frames(), fps=30.0)
    stage = Usd.Stage.Open(str(tmp_path / "perf.usd"))  # the prims live as long as the stage
    mesh = UsdGeom.Mesh(stage.GetPrimAtPath("/Face/Mesh"))
    st = UsdGeom.PrimvarsAPI(mesh).GetPrimvar("st")
    assert st.GetInterpolation() == UsdGeom.Tokens.faceVarying
    assert st.GetTypeName() == "texCoord2f[]"
    corner_uv = np.asarray(st.ComputeFlattened())  # one uv per face-vertex, polygon order
    _, _, uv_corners = _mesh().polygons()
    assert np.array_equal(corner_uv, UV[uv_corners].astype(np.float32))


def test_per_vertex_uv_is_a_vertex_st_primvar(tmp_path):
    write_usd_cache(tmp_path / "perf.usd", _mesh(per_corner=False), _frames(), fps=30.0)
    stage = Usd.Stage.Open(str(tmp_path / "perf.usd"))  # the prims live as long as the stage
    mesh = UsdGeom.Mesh(stage.GetPrimAtPath("/Face/Mesh"))
    st = UsdGeom.PrimvarsAPI(mesh).GetPrimvar("st")
    assert st.GetInterpolation() == UsdGeom.Tokens.vertex and not st.IsIndexed()
    assert np.array_equal(np.asarray(st.Get()), UV[:5].astype(np.float32))


@pytest.mark.parametrize("unit, meters", [("mm", 0.001), ("cm", 0.01), ("m", 1.0)])
def test_stage_rate_and_unit_come_from_the_performance_and_the_actor(unit, meters, tmp_path):
    write_usd_cache(tmp_path / "perf.usd", _mesh(), _frames(), fps=59.94, unit=unit)
    stage = Usd.Stage.Open(str(tmp_path / "perf.usd"))
    assert stage.GetTimeCodesPerSecond() == 59.94 and stage.GetFramesPerSecond() == 59.94
    assert UsdGeom.GetStageMetersPerUnit(stage) == meters
    assert UsdGeom.GetStageUpAxis(stage) == UsdGeom.Tokens.y
    assert stage.GetDefaultPrim().GetPath() == "/Face"


def test_maps_are_textures_of_a_preview_surface_with_paths_relative_to_the_cache(tmp_path):
    (tmp_path / "maps").mkdir()
    normals = [tmp_path / "maps" / f"normal.{f:04d}.exr" for f in range(4)]
    for file in normals:
        file.write_bytes(b"")
    textures = {"diffuseColor": "maps/albedo.png", "normal": normals, "displacement": tmp_path / "maps" / "disp.exr"}
    write_usd_cache(tmp_path / "perf.usd", _mesh(), _frames(), fps=24.0, textures=textures)
    stage = Usd.Stage.Open(str(tmp_path / "perf.usd"))
    mesh = stage.GetPrimAtPath("/Face/Mesh")
    material, _ = UsdShade.MaterialBindingAPI(mesh).ComputeBoundMaterial()
    assert material.GetPath() == "/Face/Looks/Material"
    surface = material.ComputeSurfaceSource()[0]
    assert surface.GetIdAttr().Get() == "UsdPreviewSurface"

    def texture_of(name):
        source = surface.GetInput(name).GetConnectedSources()[0][0].source
        shader = UsdShade.Shader(source.GetPrim())
        assert shader.GetIdAttr().Get() == "UsdUVTexture"
        reader = UsdShade.Shader(shader.GetInput("st").GetConnectedSources()[0][0].source.GetPrim())
        assert reader.GetIdAttr().Get() == "UsdPrimvarReader_float2"
        return shader.GetInput("file").GetAttr()

    assert texture_of("diffuseColor").Get().path == "./maps/albedo.png"
    assert texture_of("displacement").Get().path == "./maps/disp.exr"
    normal = texture_of("normal")
    assert normal.GetTimeSamples() == [0.0, 1.0, 2.0, 3.0]
    assert [normal.Get(f).path for f in range(4)] == [f"./maps/normal.{f:04d}.exr" for f in range(4)]
    # the relative path resolves next to the cache
    assert os.path.realpath(normal.Get(2).resolvedPath) == os.path.realpath(normals[2])
    assert material.GetDisplacementOutput().HasConnectedSource()


@pytest.mark.parametrize(
    "kwargs, message",
    [
        (dict(points=np.zeros((0, 5, 3))), r"points must have shape \(F, 5, 3\) with F >= 1"),
        (dict(points=np.zeros((2, 4, 3))), r"points must have shape \(F, 5, 3\)"),
        (dict(points=np.full((2, 5, 3), 1e39)), "frame 0 has a non-finite point"),
        (dict(fps=0.0), "fps must be a positive number"),
        (dict(unit="in"), "unit must be one of"),
        (dict(textures={"bump": "b.exr"}), r"unknown UsdPreviewSurface inputs \['bump'\]"),
        (dict(textures={"normal": ["a.exr"]}), "lists 1 files for 2 frames"),
    ],
)
def test_bad_input_is_refused_with_a_message(kwargs, message, tmp_path):
    arguments = dict(points=_frames(2), fps=24.0) | kwargs
    with pytest.raises(ValueError, match=message):
        write_usd_cache(tmp_path / "perf.usd", _mesh(), arguments.pop("points"), **arguments)
    assert list(tmp_path.iterdir()) == []  # nothing left behind


def test_triangles_without_uv_are_refused(tmp_path):
    mesh = Mesh(VERTICES, FACES, UV, [[0, 1, 2], [0, 2, 3], [NO_UV] * 3])
    with pytest.raises(ValueError, match="1 triangles have no uv"):
        write_usd_cache(tmp_path / "perf.usd", mesh, _frames(), fps=24.0)
