"""The parameters of performance-flow tracking, declared once (fyffe, digital_ira_course2014)."""

from __future__ import annotations

from typing import Literal

from pydantic import Field

from service.methods.params import MethodParams


class TrackingParams(MethodParams):
    """Parameters of :func:`service.methods.tracking.track.track`.

    The graph's two parameters are the paper's (§4.1: "a 4 % reduction for every temporal
    flow and a threshold value that is 20 % of the initial maximum confidence"); the term
    weights α, β, γ are 1 in the paper and here relative to the correspondence term, with the
    balancing factors of eq. 1 (shape and shrink-wrap scaled by the pose's number of graph
    edges). Defaults chosen on family a (level 0), confirmed on family b.
    """

    # §4.1 graph construction
    hat_slope: float = Field(0.04, gt=0.0, le=1.0, strict=True, description=(
        "confidence lost per temporal flow: the slope of the voting's hat function (§4.1: 4 %)"))
    stop_fraction: float = Field(0.2, gt=0.0, lt=1.0, strict=True, description=(
        "the voting stops when every confidence is below this fraction of the initial maximum "
        "(§4.1: 20 %)"))
    vote_suppression: Literal["all", "scan"] = Field("scan", description=(
        "whose confidence curves a chosen edge's hat is subtracted from: every scan's ('all') or "
        "only the chosen scan's ('scan'); graph.vote"))
    candidate_stride: int = Field(5, ge=1, le=100, strict=True, description=(
        "candidate static-to-dynamic flows go to every n-th frame (§4.1: 5)"))
    dense_scans: tuple[str, ...] = Field((), description=(
        "static scans flowed to every frame (§4.1: the eyes-closed scan, for blinks)"))
    graph_scale: float = Field(0.5, gt=0.05, le=1.0, strict=True, description=(
        "image scale of the candidate flows (§4.1: quarter resolution of HD video)"))
    region_rows: int = Field(4, ge=1, le=8, strict=True, description="facial regions: rows of the grid")
    region_cols: int = Field(3, ge=1, le=8, strict=True, description="facial regions: columns (4×3 = 12, §4.1)")
    # §4.1 flows and their confidence
    dis_preset: Literal["ultrafast", "fast", "medium"] = Field("medium", description="OpenCV DIS preset")
    dis_patch_stride: int = Field(4, ge=1, le=8, strict=True, description=(
        "DIS patch stride at the finest scale (0) of every flow. 4, not the correspondence's 2: "
        "half the CPU (0.115 against 0.221 s per 512² flow) at the same end-point error against "
        "the rendered truth's motion on family a (temporal pairs mean 0.093 against 0.096 px, "
        "scan-to-frame 0.81 against 0.87 px), confirmed on family b; finest scale 1 instead "
        "(0.051 s) is 20 % (temporal) and 40 % (scan-to-frame) worse"))
    dis_passes: int = Field(1, ge=1, le=3, strict=True, description=(
        "DIS passes (each a residual flow on the re-warped image, optical_flow.refined_flow)"))
    ncc_window: float = Field(2.0, gt=0.0, le=20.0, description="σ of the NCC window, pixels")
    ncc_smooth: float = Field(3.0, ge=0.0, le=30.0, description="σ of the NCC smoothing, pixels")
    confidence_floor: float = Field(0.75, ge=0.0, lt=1.0, description=(
        "confidence = clip((NCC − floor)/(1 − floor), 0, 1). On the rendered performances DIS "
        "succeeds almost everywhere and the NCC of the candidate flows lies in 0.8–0.99 for "
        "every scan, so the voting's hat subtraction (by the chosen flow's own confidence) "
        "wiped out all other scans; the floor restores the contrast (0: the paper's plain NCC)"))
    consistency_sigma: float = Field(0.5, ge=0.0, le=20.0, description=(
        "σ, pixels, of the forward-backward consistency weight exp(−(r/σ)²) multiplied into the "
        "confidence of every tracking edge's flows (graph.consistency; 0: off, the paper's NCC "
        "alone). Chosen on family a, confirmed on b"))
    # §5 energy
    ray_regularization: float = Field(0.01, gt=0.0, le=10.0, description=(
        "ε of eq. 4: the isotropic part added to the ray penalty I − r rᵀ (monocular depth)"))
    shape_weight: float = Field(0.1, ge=0.0, le=100.0, description=(
        "β: weight of the differential shape term (eq. 5) per graph edge of the pose"))
    artist_shape_weight: float = Field(0.05, gt=0.0, le=100.0, description=(
        "λ of eq. 6: the artist mesh's share in the blended target edge vectors"))
    wrap_weight: float = Field(1.0, ge=0.0, le=100.0, description=(
        "γ: weight of the shrink-wrap term (eq. 8) per graph edge of the static pose"))
    wrap_sigma_mm: float = Field(2.0, gt=0.0, le=50.0, description=(
        "σ of the shrink-wrap sample weight exp(−‖d − y‖²/σ²), mm (eq. 11)"))
    wrap_regularization: float = Field(0.05, gt=0.0, le=10.0, description=(
        "ε of eq. 8: the isotropic part added to the plane penalty n nᵀ"))
    certainty_gain: float = Field(2.0, gt=0.0, le=100.0, description=(
        "a pose vertex's certainty is min(1, gain · Σ incoming confidence × source certainty): "
        "the scalar belief precision min(1, det(Σ⁻¹)^⅓) of eq. 4 and 11"))
    inertia: float = Field(1e-3, gt=0.0, le=1.0, description=(
        "weight of ‖x − x_current‖² (keeps vertices no term reaches where they are)"))
    monocular_depth: bool = Field(False, strict=True, description=(
        "with one view, the rigid update (§5.6) moves each dynamic pose along the view rays "
        "to the artist mesh's size over the size region (solve.update_rigid): the head's "
        "distance from its scale. Off by default: chosen on family a, where it costs "
        "(256², 1 view: 40 frames 0.700 → 0.717 mm, 120 frames 1.273 → 1.503); family b "
        "gains (40 frames 3.177 → 1.803, 120 frames 2.480 → 2.291)"))
    monocular_size_fraction: float = Field(0.1, gt=0.0, le=1.0, description=(
        "the fraction of the face's vertices, those no static pose moves (the smallest largest "
        "residual after rigid alignment), whose size sets the head's distance in one view "
        "(solve.size_region)"))
    monocular_scale_tolerance: float = Field(0.006, ge=0.0, le=0.1, description=(
        "scale evidence within this relative band (or the static poses' own median scale "
        "change over the size region, solve.size_band, if larger) moves nothing: the soft "
        "threshold s ← 1 + sign(s − 1)·max(|s − 1| − tol, 0) (solve.update_rigid); chosen on "
        "family a (the smallest of 0 / 0.002 / 0.004 / 0.006 that costs it nothing)"))
    keyframe_iterations: int = Field(6, ge=1, le=50, strict=True, description=(
        "outer (model re-fitting) iterations of the keyframe solve (§5.1: 6 DDMS iterations)"))
    span_iterations: int = Field(3, ge=1, le=50, strict=True, description=(
        "outer iterations of each in-between span solve (§5.7: 'a few')"))
    cg_iterations: int = Field(150, ge=10, le=5000, strict=True, description=(
        "conjugate-gradient iterations per sparse solve"))
    visibility_size: int = Field(256, ge=32, le=4096, strict=True, description=(
        "longest side, pixels, of the z-buffer of the visibility test: larger views are "
        "rasterized at the reduced scale (512²: 0.042 against 0.119 s per pose and view, "
        "visibility differing by 0.005 on average, family a; no change at 256²)"))
    visibility_tolerance_mm: float = Field(2.0, gt=0.0, le=50.0, description=(
        "a vertex is visible when within this depth of the z-buffer at its pixel"))
