"""Facial scans stored as UV-space images, built from a sample actor, with their known correspondence.

The Vuvuzela setting (digital_ira_course2014, "Vuvuzela: A Facial Scan Correspondence
Tool", §"Data acquisition and preparation"): each scan is a set of images — diffuse albedo
and a point cloud (position map) — "in a cylindrically unwrapped UV space [...] the UV space
differs slightly for each expression scan". Here a scan of a frame of any sample actor
directory (``neutral.npz`` + ``performances/*.npz``, the format of
``service.samples.actor``) is made as a light stage would make it:

* **geometry**: the frame's high-resolution vertices with the head pose removed (rigid
  alignment of the head region to the neutral, :func:`~service.geometry.rigid.rigid_align_frames`);
* **layout**: a cylindrical (ear-to-ear) unwrap of the scanned face — the actor's
  ``narrow_face`` region — around a vertical axis, ``u ∝ R·atan2(x − x₀, z − z₀)``,
  ``v ∝ y``, in mm so texels are square; the unwrap sees the scan in a *perturbed* head
  frame (a seeded rotation of ``JITTER_DEG`` and shift of ``JITTER_MM``, as a scan's pose in
  the stage differs), so every scan, the neutral too, has its own layout, and skin that
  moves in the expression moves in UV;
* **maps** rasterized in that layout (:func:`~service.geometry.uv_raster.rasterize_uv`):
  ``position`` (H,W,3) mm (head frame) and ``albedo`` (H,W,3) linear RGB: the actor's
  stored albedo of that frame (blood-flow redness; low-passed) at the texel's material
  point, times pores resolved at the scan's resolution (the actor's own pore field,
  :func:`~service.samples.detail.pore_field`, whose depth and footprint follow the frame's
  local strain, :func:`~service.samples.detail.pore_height`) and a melanin speckle fixed to
  the skin (value noise in the actor's UV space).

The known correspondence (:meth:`UVScanSet.truth`): a target texel covers a point of one
triangle with barycentric coordinates b; the same material point lies in the source at
``Σ b_k layout_source[corner k]``. It is valid where that point is visible in the source
(the source's position map there agrees with the point to ``VISIBLE_MM``: fold-overs of the
unwrap — inner lips, nostrils, eyelid creases — fail this).

"User-clicked" landmarks: ``landmarks`` face vertices by farthest-point sampling on the
neutral, each clicked independently in source and target with Gaussian noise of
``click_noise_mm`` (the paper: the placement "doesn't have to be exact").
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from scipy import ndimage

from service.geometry.normals import vertex_normals
from service.geometry.rigid import rigid_align_frames
from service.geometry.uv_raster import (
    UVRaster,
    dilate,
    interpolate,
    rasterize_uv,
    sample_map,
    uv_to_texel,
)
from service.samples import dataset, detail

JITTER_DEG = 1.5          # per-scan rotation of the head frame before the unwrap (std. dev.)
JITTER_MM = 1.5           # per-scan shift of the head frame before the unwrap (std. dev.)
MARGIN = 0.04             # free border of the unit tile around the neutral's unwrap
VISIBLE_MM = 0.3          # a material point is visible in a scan if its position map agrees
SPECKLE_CELLS_UV = (1 / 1400, 1 / 600)   # melanin speckle lattice spacings, actor UV units
SPECKLE_AMPLITUDE = (0.10, 0.08)
PORE_DARKENING = 2.0      # albedo × (1 + k·pore depth mm), pore depth clipped to 0.2 mm
BASE_LOWPASS_TEXELS = 2.0  # σ removing the stored albedo's own (aliased) pores
CHUNK = 1 << 19           # texels processed at once (bounds memory at 2048²)


@dataclass(frozen=True)
class UVScan:
    """One scan as UV-space images.

    Attributes
    ----------
    name : str                  performance name (``neutral`` for the target)
    frame : int                 frame of that performance
    vertices : (n,3) float64    the frame, head pose removed, mm
    layout : (n,2) float64      this scan's UV of every mesh vertex (NaN off the scanned face)
    maps : dict                 ``albedo`` (H,W,3) float32 linear RGB, ``position`` (H,W,3)
                                float32 mm; 0 outside ``mask``
    raster : UVRaster           the layout rasterized (triangles index ``UVScanSet.faces``)
    """

    name: str
    frame: int
    vertices: np.ndarray
    layout: np.ndarray
    maps: dict
    raster: UVRaster

    @property
    def mask(self) -> np.ndarray:
        """(H,W) bool: texels the scan covers."""
        return self.raster.mask


@dataclass(frozen=True)
class UVScanSet:
    """A neutral (target) scan and expression (source) scans of one actor, with the truth.

    Attributes
    ----------
    resolution : int            maps are resolution × resolution
    faces : (m_s,3) int         the scanned triangles (mesh vertex indices)
    mesh_vertices : (n,3)       the actor's neutral: the artist mesh of the blendshapes
    mesh_faces : (m,3) int; mesh_uv : (K,2); mesh_uv_faces : (m,3)   its topology and UVs
    target : UVScan             the neutral scan
    sources : list of UVScan    one expression scan per performance
    landmark_vertices : (L,) int
    source_landmarks, target_landmarks : list of (L,2) float   clicked UVs per source pair
    """

    resolution: int
    faces: np.ndarray
    mesh_vertices: np.ndarray
    mesh_faces: np.ndarray
    mesh_uv: np.ndarray
    mesh_uv_faces: np.ndarray
    target: UVScan
    sources: list
    landmark_vertices: np.ndarray
    source_landmarks: list = field(default_factory=list)
    target_landmarks: list = field(default_factory=list)

    def truth(self, i: int) -> tuple[np.ndarray, np.ndarray]:
        """The known correspondence of source i: target texel → source texel coordinates.

        Returns
        -------
        coords : (H,W,2) float64   (column, row) in source i's maps of the material point each
                                   target texel shows (NaN outside the target's mask)
        valid : (H,W) bool         the point is visible in the source (see module docstring)
        """
        src, tgt = self.sources[i], self.target
        H = W = self.resolution
        mask = tgt.mask
        b = tgt.raster.barycentric[mask]
        corners = self.faces[tgt.raster.triangle[mask]]
        uv = np.einsum("kc,kcd->kd", b, src.layout[corners])
        xyz = np.einsum("kc,kcd->kd", b, src.vertices[corners])
        coords = np.full((H, W, 2), np.nan)
        coords[mask] = uv_to_texel(uv, H, W)
        found = sample_map(src.maps["position"], uv)
        inside = sample_map(src.mask.astype(np.float64), uv) > 0.999
        valid = np.zeros((H, W), bool)
        valid[mask] = inside & (np.linalg.norm(found - xyz, axis=1) < VISIBLE_MM)
        valid &= ndimage.binary_erosion(mask, iterations=2)
        return coords, valid


def build_uv_scans(actor_dir: str | Path, resolution: int = 1024,
                   expressions: list[str] | None = None, landmarks: int = 32,
                   click_noise_mm: float = 0.3, seed: int = 0) -> UVScanSet:
    """Scans of an actor's neutral and expression frames as UV maps (module docstring).

    Parameters
    ----------
    actor_dir : a sample actor directory (``neutral.npz``, ``performances/*.npz``)
    resolution : texels per side of every map
    expressions : performance names (default: every ``train_*`` one); each gives the frame
                  farthest from its first frame after the head pose (the expression's
                  peak). The neutral (target) scan is the first frame of the first of them
                  (the sample actor's clips start at the neutral).
    landmarks : number of clicked landmark points
    click_noise_mm : std. dev. of each click's error on the surface, mm
    seed : seeds the layout jitter and the clicks

    Returns
    -------
    UVScanSet
    """
    actor_dir = Path(actor_dir)
    actor = dataset.load_actor(actor_dir)
    V0, F = actor.vertices, actor.faces
    names = expressions if expressions is not None else dataset.performance_names(actor_dir, "train_")
    if not names:
        raise ValueError(f"{actor_dir} has no expression performances (train_*)")
    face = actor.regions.get("narrow_face")
    if face is None or not face.any():
        face = vertex_normals(V0, F)[:, 2] > 0.3
    rigid = actor.regions.get("head")
    rigid = rigid if rigid is not None and rigid.sum() >= 3 else np.ones(len(V0), bool)
    rows = np.flatnonzero(face[F].all(axis=1))           # scanned triangles: rows of F
    faces = F[rows]
    rng = np.random.default_rng([seed, 0x5CA7])
    axis, scale = _unwrap_frame(V0[face], V0[np.unique(faces)])

    frames = []                         # (name, frame, head-frame vertices, albedo map | None)
    first = _load_frames(actor_dir, names[0], V0, rigid, frame=0)
    frames.append(("neutral",) + first)
    for name in names:
        frames.append((name,) + _load_frames(actor_dir, name, V0, rigid, frame=None))
    static = _static_texture(actor, seed)
    scans = []
    Q_rest = detail.surface_strain(V0, V0, F)
    for k, (name, frame, X, albedo) in enumerate(frames):
        R, t = _jitter(rng)
        layout = np.full((len(V0), 2), np.nan)
        used = np.unique(faces)
        layout[used] = _cylindrical((X[used] - axis["centre"]) @ R.T + t, axis, scale)
        raster = rasterize_uv(layout[used].copy(), np.searchsorted(used, faces), resolution, resolution)
        position = interpolate(raster, X, faces).astype(np.float32)
        Q = detail.surface_strain(V0, X, F)
        maps = {"position": position,
                "albedo": _albedo(raster, rows, actor, static, albedo, Q, Q_rest,
                                  1.0 / (scale[0] * resolution))}
        scans.append(UVScan(name, frame, X, layout, maps, raster))

    lm = _farthest_points(V0, np.unique(faces), landmarks, rng)
    src_lm, tgt_lm = [], []
    for s in scans[1:]:
        src_lm.append(_click(s, lm, click_noise_mm, rng))
        tgt_lm.append(_click(scans[0], lm, click_noise_mm, rng))
    return UVScanSet(resolution, faces, V0, F, actor.uv, actor.uv_faces, scans[0], scans[1:],
                     lm, src_lm, tgt_lm)


def _load_frames(actor_dir: Path, name: str, V0: np.ndarray, rigid: np.ndarray,
                 frame: int | None):
    """(frame, head-frame vertices (n,3), albedo map (h,w,3) | None) of one performance."""
    with np.load(actor_dir / "performances" / f"{name}.npz") as d:
        Vs = d["vertices"].astype(np.float64)
        maps = d["map_frames"] if "albedo" in d.files and "map_frames" in d.files else None
        R, t = rigid_align_frames(Vs[:, rigid], V0[rigid])
        Vs = np.einsum("fnd,fed->fne", Vs, R) + t[:, None]          # head pose removed
        if frame is None:
            # the expression's peak: the frame farthest from the first (after the head pose)
            frame = int(np.argmax(np.linalg.norm(Vs - Vs[:1], axis=2).mean(axis=1)))
        X = Vs[frame]
        albedo = None
        if maps is not None and np.any(maps == frame):
            albedo = d["albedo"][int(np.flatnonzero(maps == frame)[0])].astype(np.float32)
    return frame, X, albedo


def _unwrap_frame(face_vertices: np.ndarray, scanned: np.ndarray):
    """The cylinder (centre, radius) and the uv scale/offset fitting the neutral's unwrap."""
    centre = np.array([face_vertices[:, 0].mean(), 0.0, face_vertices[:, 2].min() - 40.0])
    axis = {"centre": centre,
            "radius": float(np.median(np.hypot(face_vertices[:, 0] - centre[0],
                                               face_vertices[:, 2] - centre[2])))}
    uv = _cylindrical(scanned - centre, axis, None)
    lo, hi = uv.min(axis=0), uv.max(axis=0)
    s = (1 - 2 * MARGIN) / (hi - lo).max()
    offset = 0.5 - s * (lo + hi) / 2
    return axis, (s, offset)


def _cylindrical(P: np.ndarray, axis: dict, scale) -> np.ndarray:
    """UV (k,2) of points P (k,3) relative to the cylinder centre: arc length and height, mm
    (``scale`` None), or scaled into the unit tile by ``scale = (s, offset)``."""
    arc = axis["radius"] * np.arctan2(P[:, 0], P[:, 2])
    uv = np.stack([arc, P[:, 1]], axis=1)
    if scale is None:
        return uv
    s, offset = scale
    return uv * s + offset


def _jitter(rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """A small random rotation (3,3) and shift (3,) mm of the head frame."""
    w = rng.standard_normal(3) * np.deg2rad(JITTER_DEG)
    theta = np.linalg.norm(w)
    k = w / max(theta, 1e-12)
    Kx = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    R = np.eye(3) + np.sin(theta) * Kx + (1 - np.cos(theta)) * Kx @ Kx
    return R, rng.standard_normal(3) * JITTER_MM


@dataclass(frozen=True)
class _Static:
    J0: np.ndarray          # (m,3,2) rest d(position)/d(actor uv) per mesh triangle
    N0: np.ndarray          # (n,3) rest vertex normals
    gain_centre: np.ndarray  # (3,) where pores are deeper (nose tip, cheeks around it)
    seed: int


def _static_texture(actor, seed: int) -> _Static:
    V0, F, uv, UF = actor.vertices, actor.faces, actor.uv, actor.uv_faces
    dP = np.stack([V0[F[:, 1]] - V0[F[:, 0]], V0[F[:, 2]] - V0[F[:, 0]]], axis=-1)
    dU = np.stack([uv[UF[:, 1]] - uv[UF[:, 0]], uv[UF[:, 2]] - uv[UF[:, 0]]], axis=-1)
    det = dU[:, 0, 0] * dU[:, 1, 1] - dU[:, 0, 1] * dU[:, 1, 0]
    dU[np.abs(det) < 1e-14] = np.eye(2) * 1e-7          # degenerate UV triangles
    J0 = dP @ np.linalg.inv(dU)
    nose = V0[np.argmax(V0[:, 2])]
    return _Static(J0, vertex_normals(V0, F), nose, seed)


def _albedo(raster: UVRaster, rows: np.ndarray, actor, static: _Static,
            stored: np.ndarray | None, Q: np.ndarray, Q_rest: np.ndarray,
            texel_mm: float) -> np.ndarray:
    """Albedo (H,W,3) float32 of one scan: stored base × strain-dependent pores × speckle.

    Band-limited to the texel (a camera's optics do this for a real scan; point samples of
    sub-texel pores would alias into noise that differs from scan to scan): each pore's
    Gaussian profile is convolved with a Gaussian of σ = ``texel_mm``/2 (radius
    ``√(r² + 2σ²)``, depth × ``r²/(r² + 2σ²)``), and each speckle octave is attenuated by
    its Gaussian-blur gain ``exp(−2(πσ/cell)²)`` at the texel's footprint in the actor's UV.
    """
    sigma = 0.5 * texel_mm
    H, W = raster.shape
    out = np.zeros((H * W, 3), np.float32)
    idx = np.flatnonzero(raster.mask.ravel())
    if stored is not None:
        smask = np.any(stored > 0, axis=2)
        base_map = dilate(stored, smask, 4)
        base_map = ndimage.gaussian_filter(base_map, (BASE_LOWPASS_TEXELS, BASE_LOWPASS_TEXELS, 0))
    for s in range(0, len(idx), CHUNK):
        sel = idx[s:s + CHUNK]
        t = raster.triangle.ravel()[sel]
        b = raster.barycentric.reshape(-1, 3)[sel]
        mt = rows[t]                                   # the mesh triangle
        m = np.einsum("kc,kcd->kd", b, actor.uv[actor.uv_faces[mt]])          # material point
        Fv = actor.faces[mt]
        P = np.einsum("kc,kcd->kd", b, actor.vertices[Fv])
        N = np.einsum("kc,kcd->kd", b, static.N0[Fv])
        N /= np.maximum(np.linalg.norm(N, axis=1, keepdims=True), 1e-12)
        gain = 1.0 + 0.6 * np.exp(-np.sum((P - static.gain_centre) ** 2, axis=1) / (2 * 18.0 ** 2))
        J = static.J0[mt]
        pores = detail.pore_field(m, J, N, static.seed, gain)
        r2 = pores.radius.astype(np.float64) ** 2
        pores = detail.PoreField(pores.offset, pores.depth * r2 / (r2 + 2 * sigma ** 2),
                                 np.sqrt(r2 + 2 * sigma ** 2), pores.normal)
        # the texel's σ in actor-UV units: mm / (mm per uv unit, the Jacobian's area scale)
        JtJ = np.einsum("kia,kib->kab", J, J)
        mm_per_uv = np.sqrt(np.sqrt(np.maximum(JtJ[:, 0, 0] * JtJ[:, 1, 1] - JtJ[:, 0, 1] ** 2, 1e-12)))
        sigma_uv = sigma / mm_per_uv
        Qt = np.einsum("kc,kcq->qk", b, Q[Fv])
        Qr = np.einsum("kc,kcq->qk", b, Q_rest[Fv])
        pore, _ = detail.pore_height(pores, Qt, Qr)
        base = (sample_map(base_map, m) if stored is not None
                else np.broadcast_to(detail.SKIN_BASE, (len(sel), 3)))
        speck = np.ones(len(sel))
        for cell, amp in zip(SPECKLE_CELLS_UV, SPECKLE_AMPLITUDE):
            gain_blur = np.exp(-2 * (np.pi * sigma_uv / cell) ** 2)
            speck *= 1.0 - amp * gain_blur * _value_noise(m / cell, static.seed + int(1 / cell))
        a = base * (1.0 + PORE_DARKENING * np.clip(pore, -0.2, 0.0))[:, None] * speck[:, None]
        out[sel] = np.clip(a, 0.0, 1.0)
    return out.reshape(H, W, 3)


def _value_noise(p: np.ndarray, seed: int) -> np.ndarray:
    """Smooth value noise in [0,1) at lattice coordinates p (k,2): hashed lattice values,
    smoothstep-interpolated."""
    i = np.floor(p).astype(np.int64)
    f = p - i
    f = f * f * (3 - 2 * f)

    def h(dx, dy):
        key = (i[:, 0] + dx) * 1_000_003 + (i[:, 1] + dy)
        z = key.astype(np.uint64) * np.uint64(0x9E3779B97F4A7C15) + np.uint64(seed * 0x632BE59BD9B4E019 % 2**64)
        z = (z ^ (z >> np.uint64(30))) * np.uint64(0xBF58476D1CE4E5B9)
        z = (z ^ (z >> np.uint64(27))) * np.uint64(0x94D049BB133111EB)
        return ((z ^ (z >> np.uint64(31))) >> np.uint64(11)).astype(np.float64) / float(2**53)

    top = h(0, 0) * (1 - f[:, 0]) + h(1, 0) * f[:, 0]
    bottom = h(0, 1) * (1 - f[:, 0]) + h(1, 1) * f[:, 0]
    return top * (1 - f[:, 1]) + bottom * f[:, 1]


def _farthest_points(V: np.ndarray, candidates: np.ndarray, k: int,
                     rng: np.random.Generator) -> np.ndarray:
    """k vertex indices by farthest-point sampling (Euclidean) among the candidates."""
    P = V[candidates]
    chosen = [int(rng.integers(len(P)))]
    d = np.linalg.norm(P - P[chosen[0]], axis=1)
    for _ in range(k - 1):                       # a loop over the k landmarks, not vertices
        j = int(np.argmax(d))
        chosen.append(j)
        d = np.minimum(d, np.linalg.norm(P - P[j], axis=1))
    return candidates[np.array(chosen)]


def _click(scan: UVScan, vertices: np.ndarray, noise_mm: float,
           rng: np.random.Generator) -> np.ndarray:
    """Clicked UVs (L,2) of vertices in a scan: the vertex's UV plus noise of noise_mm on the
    surface (converted with the map's local texel size)."""
    uv = scan.layout[vertices]
    H = scan.raster.shape[0]
    noise = rng.standard_normal((len(uv), 2)) * noise_mm / mm_per_texel(scan)
    return uv + noise / H


def mm_per_texel(scan: UVScan) -> float:
    """Median texel size (mm) of a scan, from its position map's finite differences."""
    pos, m = scan.maps["position"], scan.mask
    both = m[:, 1:] & m[:, :-1]
    return float(np.median(np.linalg.norm(pos[:, 1:] - pos[:, :-1], axis=2)[both]))
