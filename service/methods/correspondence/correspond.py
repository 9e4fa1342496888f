"""Scan correspondence in UV space: Vuvuzela's three steps, as one function.

digital_ira_course2014, "Vuvuzela: A Facial Scan Correspondence Tool", §"Correspondence
algorithm": (1) a Delaunay triangulation of the user's landmark points and a piecewise-affine
pre-warp of the source diffuse texture to the target (:mod:`.prewarp`); (2) a dense optical
flow from the pre-warped source diffuse texture to the target (on over-sharpened textures,
with occlusion masks and pinned points painted black: :mod:`.texture`;
:mod:`service.geometry.optical_flow`); (3) the composed warp applied to every source map
(diffuse, specular, normals, point cloud), giving the source scan in the target's UV space.

Composition: with A the pre-warp (target texel → source coordinates) and f the flow on the
target grid (``prewarped(x + f(x)) ≈ target(x)``), the source coordinates of target texel x
are ``A(x + f(x))``, evaluated by bilinear lookup of the dense map A (A is continuous and
piecewise affine, so the lookup is exact inside triangles and off by < 1e-3 texel at its
kinks); every map is then resampled once from the original source, never twice.

Departures from the paper: the flow is OpenCV's DIS run to the finest scale with a residual
pass on the re-warped source (:func:`~service.geometry.optical_flow.refined_flow`) on the
CPU, not the GPU flow of the course (FlowLib, which the tracking paper of the same course
names); the confidence of the result is the NCC of fyffe §4.1 (same course), which the
Vuvuzela paper does not compute; pinned points are drawn at the *target* landmark position
in both the target and the pre-warped source texture (the pre-warp carries a source
landmark exactly there, so this is the same dot without a second resampling).
"""

from __future__ import annotations

import time
from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np

from service.geometry import optical_flow as of
from service.geometry.uv_raster import uv_to_texel
from service.methods.correspondence.params import CorrespondenceParams
from service.methods.correspondence.prewarp import piecewise_affine_coords
from service.methods.correspondence.texture import flow_texture, pin_dots
from service.methods.inputs import InvalidInput, Progress, no_progress

#: the map the flow is computed on (the diffuse albedo)
DIFFUSE = "albedo"
#: optional (H,W) bool entry of a map set: the texels the scan covers
COVERAGE = "mask"


@dataclass(frozen=True)
class CorrespondenceResult:
    """The source scan in the target's UV space.

    Attributes
    ----------
    maps : dict name → (H,W) or (H,W,C) float32   every source map resampled onto the target
                                                  grid (0 where ``mask`` is False)
    coords : (H,W,2) float32    source texel (column, row) of every target texel: the warp
    prewarp : (H,W,2) float32   the pre-warp's source coordinates (identity if disabled)
    flow : (H,W,2) float32      the flow on the target grid (pre-warped source → target)
    confidence : (H,W) float32  NCC of the target and warped source flow textures, in [0,1]
    mask : (H,W) bool           target texels whose source coordinates fall on covered
                                source texels
    seconds : dict stage → s
    """

    maps: dict
    coords: np.ndarray
    prewarp: np.ndarray
    flow: np.ndarray
    confidence: np.ndarray
    mask: np.ndarray
    seconds: dict


def correspond(source_maps: Mapping[str, np.ndarray], target_maps: Mapping[str, np.ndarray],
               landmarks: np.ndarray, params: CorrespondenceParams | None = None,
               progress: Progress = no_progress, pinned: np.ndarray | None = None,
               source_occlusion: np.ndarray | None = None,
               target_occlusion: np.ndarray | None = None) -> CorrespondenceResult:
    """Warp a source scan into a target scan's UV space (Vuvuzela, module docstring).

    Parameters
    ----------
    source_maps : name → (h,w) or (h,w,C) float   the source scan's maps, all of one size;
                  ``albedo`` (h,w,3) (or (h,w)) is required (the diffuse texture the
                  correspondence is computed on); others (``position`` (h,w,3) mm,
                  ``specular``, ``normal``, ...) are warped alike; an optional ``mask``
                  (h,w) bool marks covered texels (default: albedo non-zero)
    target_maps : name → maps of the target scan (H,W); only ``albedo`` and ``mask`` are used
    landmarks : (L,2,2) float   clicked corresponding points, UV unit-tile coordinates (API.md
                convention): ``landmarks[:, 0]`` in the source, ``landmarks[:, 1]`` in the
                target; at least 3 when ``params.prewarp``
    params : CorrespondenceParams (default: its defaults)
    progress : Progress
    pinned : (P,) int | None    landmarks (rows of ``landmarks``) that are pinned: drawn as
                                black dots of ``params.pin_radius`` into both flow textures
    source_occlusion, target_occlusion : (h,w), (H,W) bool | None   painted occlusion masks

    Returns
    -------
    CorrespondenceResult

    Raises
    ------
    InvalidInput   missing albedo, maps of mixed sizes, bad landmarks
    """
    params = params or CorrespondenceParams()
    seconds = {}
    t0 = time.perf_counter()
    src_mask, (h, w) = _maps_and_mask(source_maps, "source")
    tgt_mask, (H, W) = _maps_and_mask(target_maps, "target")
    lm = np.asarray(landmarks, dtype=np.float64)
    if lm.ndim != 3 or lm.shape[1:] != (2, 2):
        raise InvalidInput(f"landmarks must be (L,2,2) (point, source/target, uv), got {lm.shape}")
    src_xy, tgt_xy = uv_to_texel(lm[:, 0], h, w), uv_to_texel(lm[:, 1], H, W)
    pins = np.zeros(0, np.int64) if pinned is None else np.asarray(pinned, np.int64).ravel()
    if len(pins) and (pins.min() < 0 or pins.max() >= len(lm)):
        raise InvalidInput(f"pinned landmark indices must be in [0, {len(lm)}), got "
                           f"{pins.min()}..{pins.max()}")
    for name, occ, shape in (("source_occlusion", source_occlusion, (h, w)),
                             ("target_occlusion", target_occlusion, (H, W))):
        if occ is not None and np.shape(occ) != shape:
            raise InvalidInput(f"{name} must be {shape}, got {np.shape(occ)}")

    progress(0.0, "pre-warp")
    if params.prewarp:
        A = piecewise_affine_coords(src_xy, tgt_xy, (H, W)).astype(np.float32)
    else:
        A = of.flow_to_coords(np.zeros((H, W, 2), np.float32))
        if (h, w) != (H, W):                               # same UV, another resolution
            A = (A + 0.5) * np.array([w / W, h / H], np.float32) - 0.5
    seconds["prewarp"] = time.perf_counter() - t0

    t1 = time.perf_counter()
    progress(0.2, "flow textures")
    src_tex = flow_texture(source_maps[DIFFUSE], src_mask, params.sharpen_sigma,
                           params.sharpen_amount, source_occlusion)
    tgt_tex = flow_texture(target_maps[DIFFUSE], tgt_mask, params.sharpen_sigma,
                           params.sharpen_amount, target_occlusion,
                           tgt_xy[pins] if len(pins) else None, params.pin_radius)
    # bicubic: a bilinear pre-warp blurs the source's pores and biases the flow (the 8
    # level-1 sample pairs at 1024², benchmarks/correspondence_report.py: pooled median
    # 0.058 -> 0.050 texel; the 95th percentile 0.35 -> 0.38)
    pre_tex = of.remap(src_tex, A, border=0.0, cubic=True)
    if len(pins):
        pre_tex[pin_dots(tgt_xy[pins], (H, W), params.pin_radius)] = 0.0
    tgt8, pre8 = of.to_uint8(tgt_tex, pre_tex, tgt_mask)
    seconds["textures"] = time.perf_counter() - t1

    t2 = time.perf_counter()
    progress(0.35, f"flow ({params.flow})")
    if params.flow == "refined":
        flow = of.refined_flow(tgt8, pre8, passes=params.dis_passes, preset=params.dis_preset,
                               patch_size=params.patch_size, patch_stride=params.patch_stride,
                               refinement_iterations=params.refinement_iterations,
                               smoothness=params.smoothness)
    elif params.flow == "dis":
        flow = of.dis_flow(tgt8, pre8, params.dis_preset)
    elif params.flow == "farneback":
        flow = of.farneback_flow(tgt8, pre8)
    else:
        flow = np.zeros((H, W, 2), np.float32)
    seconds["flow"] = time.perf_counter() - t2

    t3 = time.perf_counter()
    progress(0.8, "warping the maps")
    coords = of.remap(A, of.flow_to_coords(flow))            # A(x + f(x))
    inside = of.remap(src_mask.astype(np.float32), coords, border=0.0) > 0.999
    mask = tgt_mask & inside
    maps = {}
    for name, m in source_maps.items():
        if name == COVERAGE:
            continue
        out = of.remap(np.asarray(m, np.float32), coords, border=0.0)
        out[~mask] = 0.0
        maps[name] = out
    warped_tex = of.remap(src_tex, coords, border=0.0)
    confidence = of.ncc_confidence(tgt_tex, warped_tex, params.confidence_window,
                                   params.confidence_smoothing, mask)
    seconds["warp"] = time.perf_counter() - t3
    seconds["total"] = time.perf_counter() - t0
    progress(1.0, "done")
    return CorrespondenceResult(maps, coords.astype(np.float32), A, flow.astype(np.float32),
                                confidence, mask, seconds)


def _maps_and_mask(maps: Mapping[str, np.ndarray], which: str):
    if DIFFUSE not in maps:
        raise InvalidInput(f"the {which} scan needs an {DIFFUSE!r} map (the diffuse texture the "
                           f"correspondence is computed on); got {sorted(maps)}")
    shape = np.shape(maps[DIFFUSE])[:2]
    if len(shape) != 2 or min(shape) < 8:
        raise InvalidInput(f"the {which} {DIFFUSE!r} map must be (H,W[,C]) with H, W >= 8, "
                           f"got {np.shape(maps[DIFFUSE])}")
    for name, m in maps.items():
        if np.shape(m)[:2] != shape:
            raise InvalidInput(f"the {which} map {name!r} is {np.shape(m)[:2]}, expected "
                               f"{shape} like its {DIFFUSE!r}")
    if COVERAGE in maps:
        mask = np.asarray(maps[COVERAGE], bool)
        if mask.ndim != 2:
            raise InvalidInput(f"the {which} {COVERAGE!r} must be (H,W) bool")
    else:
        a = np.asarray(maps[DIFFUSE], dtype=np.float64)
        mask = (a.reshape(*shape, -1) != 0).any(axis=2)
    if not mask.any():
        raise InvalidInput(f"the {which} scan covers no texel")
    return mask, shape
