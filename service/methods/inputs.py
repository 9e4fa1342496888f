"""What every method trains from: the actor's neutral with markers, and captured clips.

Plain dataclasses over NumPy arrays (DESIGN.md: ``train(actor, clips, params, progress)``).
Validation raises :class:`InvalidInput` (a ``ValueError``; the API maps it to 422) with a
message naming the clip, frame or marker and what was expected.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable, Mapping

import numpy as np

from service.errors import InvalidInput
from service.geometry.closest_point import surface_points

#: progress callback of long work: (fraction 0..1, stage name)
Progress = Callable[[float, str], None]


def no_progress(fraction: float, stage: str) -> None:
    """A :data:`Progress` that ignores its reports."""


@dataclass(frozen=True)
class ActorData:
    """The actor's high-resolution neutral, its UV layout and its marker layout.

    Attributes
    ----------
    vertices : (n,3) float      neutral, in the actor's unit (mm for the sample actor)
    faces : (m,3) int
    uv : (K,2) float            UVs in the unit tile; uv_faces (m,3) per-corner indices
    uv_faces : (m,3) int
    marker_triangle : (M,) int  each marker as a surface point: triangle ...
    marker_barycentric : (M,3)  ... and barycentric coordinates (non-negative, sum 1)
    marker_names : tuple of M str
    regions : name → (n,) bool  optional named vertex sets for per-region metrics
    """

    vertices: np.ndarray
    faces: np.ndarray
    uv: np.ndarray
    uv_faces: np.ndarray
    marker_triangle: np.ndarray
    marker_barycentric: np.ndarray
    marker_names: tuple[str, ...]
    regions: Mapping[str, np.ndarray] = field(default_factory=dict)

    @property
    def n_vertices(self) -> int:
        return len(self.vertices)

    @property
    def n_markers(self) -> int:
        return len(self.marker_triangle)

    def marker_positions(self, V: np.ndarray | None = None) -> np.ndarray:
        """Marker positions (…,M,3) on vertices V (…,n,3) (default: the neutral)."""
        V = self.vertices if V is None else V
        return surface_points(V, self.faces, self.marker_triangle, self.marker_barycentric)

    def marker_uv(self) -> np.ndarray:
        """Texture coordinates (M,2) of the markers."""
        return surface_points(self.uv, self.uv_faces, self.marker_triangle, self.marker_barycentric)


@dataclass(frozen=True)
class Clip:
    """A captured training clip, in vertex correspondence with the neutral.

    Attributes
    ----------
    name : str
    vertices : (F,n,3) float        world-space high-resolution frames
    markers : (F,M,3) float         world-space markers in layout order, NaN when occluded
    displacement : (F,H,W) or None  fine-scale detail along the normal *relative to
                                    vertices* (a scan delivered as mesh + displacement map)
    albedo : (F,H,W,3) or None      diffuse albedo maps, linear RGB
    fps : float
    """

    name: str
    vertices: np.ndarray
    markers: np.ndarray
    displacement: np.ndarray | None = None
    albedo: np.ndarray | None = None
    fps: float = 30.0

    @property
    def frames(self) -> int:
        return len(self.markers)


def check_clips(actor: ActorData, clips: list[Clip], mixed_maps: bool = False) -> None:
    """Raise :class:`InvalidInput` unless every clip matches the actor and the others.

    The clips that carry displacement (or albedo) maps must agree in their size; unless
    ``mixed_maps``, either every clip carries a kind of map or none does (a method that
    uses maps where clips have them, e.g. shape space, passes ``mixed_maps=True``).
    """
    if not clips:
        raise InvalidInput("training needs at least one clip")
    n, M = actor.n_vertices, actor.n_markers
    for c in clips:
        if c.markers.ndim != 3 or c.markers.shape[1:] != (M, 3):
            raise InvalidInput(f"clip '{c.name}': markers must be (F,{M},3), got {c.markers.shape}")
        if c.vertices.shape != (c.frames, n, 3):
            raise InvalidInput(f"clip '{c.name}': vertices must be ({c.frames},{n},3) "
                               f"(frames, the neutral's vertex count), got {c.vertices.shape}")
        bad = np.flatnonzero(~np.isfinite(c.vertices).all(axis=(1, 2)))
        if len(bad):
            raise InvalidInput(f"clip '{c.name}' frame {bad[0]} has non-finite vertices")
        for key in ("displacement", "albedo"):
            x = getattr(c, key)
            if x is not None and len(x) != c.frames:
                raise InvalidInput(f"clip '{c.name}': {key} has {len(x)} frames, markers {c.frames}")
    for key, ndim in (("displacement", 3), ("albedo", 4)):
        given = [getattr(c, key) is not None for c in clips]
        if not mixed_maps and any(given) and not all(given):
            raise InvalidInput(f"{key} maps must be given for every clip or for none "
                               f"(missing in '{clips[given.index(False)].name}')")
        shapes = {getattr(c, key).shape[1:] for c in clips if getattr(c, key) is not None}
        if len(shapes) > 1:
            raise InvalidInput(f"{key} maps differ in size between clips: {sorted(shapes)}")
        for shape in shapes:
            if len(shape) != ndim - 1 or shape[0] != shape[1] or (ndim == 4 and shape[2] != 3):
                raise InvalidInput(f"{key} maps must be square, (F,H,H{',3' if ndim == 4 else ''}), "
                                   f"got (F,{','.join(map(str, shape))})")
