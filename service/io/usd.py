"""A performance as one USD point cache: a mesh with time-sampled points, UVs and its maps.

Pipelines take one cache per performance rather than one OBJ per frame. The stage written by
:func:`write_usd_cache` holds (OpenUSD schemas, written with ``usd-core``):

- ``/Face`` (an ``Xform``, the default prim) and ``/Face/Mesh``, a ``UsdGeom.Mesh`` whose
  topology is authored once (``faceVertexCounts``/``faceVertexIndices``: the file polygons, so
  quads stay quads, from :meth:`Mesh.polygons`) and whose ``points`` (and ``extent``) are
  time-sampled, one sample per frame, as float32 — USD's point type; ``subdivisionScheme`` is
  ``none`` (the mesh is the final surface, not a subdivision cage);
- the primvar ``st`` (``texCoord2f[]``): ``vertex`` interpolation for per-vertex UVs, indexed
  ``faceVarying`` for per-corner UVs (UV seams);
- optionally ``/Face/Looks/Material``, a ``UsdPreviewSurface`` whose inputs (``diffuseColor``,
  ``normal``, ``displacement``, ...) read ``UsdUVTexture`` shaders on the ``st`` primvar. Each
  texture's ``inputs:file`` is a path relative to the ``.usd`` file (``./maps/...``), one path
  for the whole performance or one per frame (time-sampled, for per-frame detail maps);
- stage metadata: ``timeCodesPerSecond`` and ``framesPerSecond`` from the frame rate, start
  and end time codes, ``metersPerUnit`` from the actor's length unit (mm -> 0.001) and ``upAxis``
  Y.

The stage is built in memory and exported to a temporary sibling that is renamed into place,
so a reader never sees half a cache.
"""

from __future__ import annotations

import math
import os
import tempfile
from pathlib import Path
from typing import Mapping, Sequence, Union

import numpy as np
from pxr import Gf, Sdf, Usd, UsdGeom, UsdShade, Vt

from service.io.triangle_mesh import NO_UV, Mesh

METERS_PER_UNIT = {"mm": 0.001, "cm": 0.01, "m": 1.0}
"""Stage ``metersPerUnit`` for the length units an actor may use."""

COLOR_INPUTS = ("diffuseColor", "emissiveColor", "specularColor", "normal")
"""UsdPreviewSurface inputs of type color3f/normal3f, read from a texture's ``rgb`` output."""
FLOAT_INPUTS = ("displacement", "roughness", "metallic", "occlusion", "opacity", "clearcoat",
                "clearcoatRoughness", "ior")
"""UsdPreviewSurface inputs of type float, read from a texture's ``r`` output."""

TexturePath = Union[str, os.PathLike]

_ROOT, _MESH, _LOOKS = "/Face", "/Face/Mesh", "/Face/Looks"


def write_usd_cache(
    path: str | os.PathLike,
    mesh: Mesh,
    points: np.ndarray,
    *,
    fps: float,
    unit: str = "mm",
    textures: Mapping[str, TexturePath | Sequence[TexturePath]] | None = None,
    start_frame: int = 0,
) -> None:
    """Write a performance as one USD stage: topology once, points per frame, UVs, maps.

    Parameters
    ----------
    path : path ending ``.usd``, ``.usdc`` (binary crate) or ``.usda`` (text)
    mesh : Mesh
        Topology and UVs (``uv``, optionally per-corner ``uv_faces``); polygons are rebuilt
        from ``quad_split``. Its ``vertices`` are not written (the frames are).
    points : (F,V,3) float
        Vertex positions of every frame in the actor's `unit`, V = ``len(mesh.vertices)``;
        stored as float32.
    fps : float
        Frames per second: ``timeCodesPerSecond`` and ``framesPerSecond``; frame f is time code
        ``start_frame + f``.
    unit : {"mm", "cm", "m"}
        The actor's length unit, stored as ``metersPerUnit``.
    textures : dict, optional
        UsdPreviewSurface input name (one of :data:`COLOR_INPUTS` or :data:`FLOAT_INPUTS`) ->
        texture file, or a sequence of F files (one per frame, time-sampled). Relative paths
        are taken relative to the directory of `path`; absolute ones are made relative to it.
        Needs UVs.
    start_frame : int
        Time code of the first frame.

    Raises
    ------
    ValueError
        For points of the wrong shape or not finite, a frame rate that is not positive, an
        unknown unit or texture input, textures without UVs or with a per-frame list of the
        wrong length, a mesh with triangles lacking UVs (``NO_UV`` rows), or a suffix USD does
        not write.
    """
    path = Path(path)
    if path.suffix not in (".usd", ".usdc", ".usda"):
        raise ValueError(f"a USD cache path ends .usd, .usdc or .usda, got {path.name!r}")
    points = np.asarray(points)
    vertex_count = len(mesh.vertices)
    if points.ndim != 3 or points.shape[1:] != (vertex_count, 3) or len(points) == 0:
        raise ValueError(
            f"points must have shape (F, {vertex_count}, 3) with F >= 1, got {points.shape}"
        )
    if points.dtype.kind not in "fiu":
        raise ValueError(f"points must be real numbers, got dtype {points.dtype}")
    with np.errstate(over="ignore"):  # beyond float32 range: inf, refused below
        points = np.ascontiguousarray(points, dtype=np.float32)
    if not np.isfinite(points).all():
        frame = int(np.argmax(~np.isfinite(points).all(axis=(1, 2))))
        raise ValueError(f"frame {frame} has a non-finite point (or one beyond float32 range)")
    if not (math.isfinite(fps) and fps > 0):
        raise ValueError(f"fps must be a positive number, got {fps}")
    if unit not in METERS_PER_UNIT:
        raise ValueError(f"unit must be one of {sorted(METERS_PER_UNIT)}, got {unit!r}")
    if mesh.uv_faces is not None and (mesh.uv_faces == NO_UV).any():
        raise ValueError(
            f"{int((mesh.uv_faces[:, 0] == NO_UV).sum())} triangles have no uv; a USD st "
            "primvar needs uv at every corner"
        )
    textures = dict(textures or {})
    unknown = sorted(set(textures) - set(COLOR_INPUTS) - set(FLOAT_INPUTS))
    if unknown:
        raise ValueError(
            f"unknown UsdPreviewSurface inputs {unknown}; expected some of "
            f"{list(COLOR_INPUTS + FLOAT_INPUTS)}"
        )
    if textures and mesh.uv is None:
        raise ValueError("textures need UVs; the mesh has none")

    stage = Usd.Stage.CreateInMemory()
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.y)
    UsdGeom.SetStageMetersPerUnit(stage, METERS_PER_UNIT[unit])
    stage.SetTimeCodesPerSecond(float(fps))
    stage.SetFramesPerSecond(float(fps))
    stage.SetStartTimeCode(start_frame)
    stage.SetEndTimeCode(start_frame + len(points) - 1)
    root = UsdGeom.Xform.Define(stage, _ROOT)
    stage.SetDefaultPrim(root.GetPrim())

    usd_mesh = UsdGeom.Mesh.Define(stage, _MESH)
    sizes, corners, uv_corners = mesh.polygons()
    usd_mesh.CreateFaceVertexCountsAttr(Vt.IntArray.FromNumpy(sizes.astype(np.int32)))
    usd_mesh.CreateFaceVertexIndicesAttr(Vt.IntArray.FromNumpy(corners.astype(np.int32)))
    usd_mesh.CreateSubdivisionSchemeAttr(UsdGeom.Tokens.none)
    usd_mesh.CreateOrientationAttr(UsdGeom.Tokens.rightHanded)
    points_attr, extent_attr = usd_mesh.CreatePointsAttr(), usd_mesh.CreateExtentAttr()
    low, high = points.min(axis=1), points.max(axis=1)
    for f, frame in enumerate(points):
        time = Usd.TimeCode(start_frame + f)
        points_attr.Set(Vt.Vec3fArray.FromNumpy(frame), time)
        extent_attr.Set(Vt.Vec3fArray([Gf.Vec3f(*low[f].tolist()), Gf.Vec3f(*high[f].tolist())]),
                        time)

    if mesh.uv is not None:
        primvars = UsdGeom.PrimvarsAPI(usd_mesh)
        interpolation = UsdGeom.Tokens.vertex if mesh.uv_faces is None else UsdGeom.Tokens.faceVarying
        st = primvars.CreatePrimvar("st", Sdf.ValueTypeNames.TexCoord2fArray, interpolation)
        st.Set(Vt.Vec2fArray.FromNumpy(np.ascontiguousarray(mesh.uv, dtype=np.float32)))
        if mesh.uv_faces is not None:
            st.SetIndices(Vt.IntArray.FromNumpy(uv_corners.astype(np.int32)))
    if textures:
        _material(stage, usd_mesh, textures, path.parent, len(points), start_frame)
    export_stage(stage, path)


def _material(stage, usd_mesh, textures: dict, directory: Path, frames: int, start: int) -> None:
    """A UsdPreviewSurface reading every texture on the ``st`` primvar, bound to the mesh."""
    material = UsdShade.Material.Define(stage, f"{_LOOKS}/Material")
    surface = UsdShade.Shader.Define(stage, f"{_LOOKS}/Material/PreviewSurface")
    surface.CreateIdAttr("UsdPreviewSurface")
    material.CreateSurfaceOutput().ConnectToSource(surface.ConnectableAPI(), "surface")
    if "displacement" in textures:
        material.CreateDisplacementOutput().ConnectToSource(surface.ConnectableAPI(), "displacement")
    reader = UsdShade.Shader.Define(stage, f"{_LOOKS}/Material/stReader")
    reader.CreateIdAttr("UsdPrimvarReader_float2")
    st_name = material.CreateInput("frame:stPrimvarName", Sdf.ValueTypeNames.Token)
    st_name.Set("st")
    reader.CreateInput("varname", Sdf.ValueTypeNames.Token).ConnectToSource(st_name)
    for name, files in sorted(textures.items()):
        texture = UsdShade.Shader.Define(stage, f"{_LOOKS}/Material/{name}Texture")
        texture.CreateIdAttr("UsdUVTexture")
        texture.CreateInput("st", Sdf.ValueTypeNames.Float2).ConnectToSource(
            reader.ConnectableAPI(), "result"
        )
        texture.CreateInput("sourceColorSpace", Sdf.ValueTypeNames.Token).Set(
            "sRGB" if name == "diffuseColor" else "raw"
        )
        file_input = texture.CreateInput("file", Sdf.ValueTypeNames.Asset)
        if isinstance(files, (str, os.PathLike)):
            file_input.Set(Sdf.AssetPath(_relative(files, directory)))
        else:
            files = list(files)
            if len(files) != frames:
                raise ValueError(
                    f"texture '{name}' lists {len(files)} files for {frames} frames; give one "
                    "file, or one per frame"
                )
            for f, file in enumerate(files):
                file_input.Set(Sdf.AssetPath(_relative(file, directory)), Usd.TimeCode(start + f))
        if name in COLOR_INPUTS:
            value_type = Sdf.ValueTypeNames.Normal3f if name == "normal" else Sdf.ValueTypeNames.Color3f
            output = texture.CreateOutput("rgb", Sdf.ValueTypeNames.Float3)
        else:
            value_type = Sdf.ValueTypeNames.Float
            output = texture.CreateOutput("r", Sdf.ValueTypeNames.Float)
        surface.CreateInput(name, value_type).ConnectToSource(output)
    UsdShade.MaterialBindingAPI.Apply(usd_mesh.GetPrim()).Bind(material)


def _relative(file: TexturePath, directory: Path) -> str:
    """``./``-relative POSIX path of a texture from the cache's directory."""
    file = Path(file)
    if file.is_absolute():
        file = Path(os.path.relpath(file, directory.resolve()))
    text = file.as_posix()
    return text if text.startswith(("./", "../")) else f"./{text}"


def export_stage(stage, path: Path) -> None:
    """Export the stage to a temporary sibling (same suffix, so the same format), then rename."""
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.stem}.", suffix=path.suffix, dir=path.parent)
    os.close(fd)
    try:
        if not stage.GetRootLayer().Export(tmp):
            raise OSError(f"USD could not write {path}")
        os.chmod(tmp, 0o644)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
