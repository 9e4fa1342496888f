"""The sample actor's files (written by ``facesynth sample-actor``) as method inputs.

:func:`load_actor` gives the :class:`~service.methods.inputs.ActorData`, :func:`load_clip`
a :class:`~service.methods.inputs.Clip` of one performance, as a capture system would
deliver it: the high-resolution mesh (``vertices``: the medium surface with the wrinkles
at vertex resolution) plus a fine displacement map **relative to that mesh**. The sample
actor's ``displacement`` maps hold the whole detail (wrinkles and pores) relative to the
medium surface ``vertices_medium``, so the part the mesh already carries, the normal
offset ``n · (vertices − vertices_medium)`` interpolated into the map, is subtracted;
otherwise the wrinkles would be counted twice.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from service.geometry.normals import vertex_normals
from service.geometry.uv_raster import interpolation_matrix, rasterize_uv
from service.io.markers import read_marker_layout
from service.methods.inputs import ActorData, Clip

#: vertex regions of the sample actor's skin (``neutral.npz`` key ``region``)
REGIONS = {"narrow_face": (0,), "face": (0, 1), "head": (2,)}


def load_actor(actor_dir: str | Path) -> ActorData:
    """The sample actor's neutral, UV layout, markers and regions."""
    actor_dir = Path(actor_dir)
    with np.load(actor_dir / "neutral.npz") as d:
        V, F = d["vertices"].astype(np.float64), d["faces"].astype(np.int64)
        uv, uvf, region = d["uv"].astype(np.float64), d["uv_faces"].astype(np.int64), d["region"]
    layout = read_marker_layout(actor_dir / "markers.json")
    return ActorData(V, F, uv, uvf, layout.triangle, layout.barycentric, tuple(layout.names),
                     {name: np.isin(region, ids) for name, ids in REGIONS.items()})


def performance_names(actor_dir: str | Path, prefix: str = "") -> list[str]:
    """Names of the stored performances (file stems), sorted, optionally by prefix."""
    return sorted(p.stem for p in (Path(actor_dir) / "performances").glob(f"{prefix}*.npz"))


def map_frames(actor_dir: str | Path, name: str) -> np.ndarray:
    """Frame indices (k,) of a performance that have ground-truth maps."""
    with np.load(Path(actor_dir) / "performances" / f"{name}.npz") as d:
        return d["map_frames"] if "displacement" in d.files else np.zeros(0, np.int64)


def load_clip(actor_dir: str | Path, name: str, actor: ActorData | None = None,
              frames: np.ndarray | None = None) -> Clip:
    """One performance as a :class:`Clip`; maps only if every selected frame has them.

    Parameters
    ----------
    actor_dir : the sample actor's directory;  name : performance name (file stem)
    actor : the loaded actor (default: loaded here; needed for the map relative to the mesh)
    frames : (k,) int   frames to take (default all)
    """
    actor = actor or load_actor(actor_dir)
    with np.load(Path(actor_dir) / "performances" / f"{name}.npz") as d:
        nf = len(d["markers"])
        sel = np.arange(nf) if frames is None else np.asarray(frames, np.int64)
        vertices = d["vertices"][sel].astype(np.float64)
        markers = d["markers"][sel].astype(np.float64)
        fps = float(d["fps"])
        displacement = albedo = None
        if "displacement" in d.files:
            slot = {int(f): i for i, f in enumerate(d["map_frames"])}
            if all(int(f) in slot for f in sel):
                rows = [slot[int(f)] for f in sel]
                displacement = d["displacement"][rows].astype(np.float32)
                albedo = d["albedo"][rows].astype(np.float32)
                medium = d["vertices_medium"][sel].astype(np.float64)
    if displacement is not None:
        displacement -= vertex_detail_map(actor, vertices, medium, displacement.shape[1])
    return Clip(name, vertices, markers, displacement, albedo, fps)


def vertex_detail_map(actor: ActorData, vertices: np.ndarray, medium: np.ndarray, H: int) -> np.ndarray:
    """The normal offset ``n(medium) · (vertices − medium)`` (F,n) interpolated into H×H maps (F,H,H)."""
    N = vertex_normals(medium, actor.faces, weighting="area")
    h = np.einsum("fnd,fnd->nf", vertices - medium, N)
    raster = rasterize_uv(actor.uv, actor.uv_faces, H, H)
    P = interpolation_matrix(raster, actor.faces, actor.n_vertices)
    return (P @ h).T.reshape(-1, H, H).astype(np.float32)
