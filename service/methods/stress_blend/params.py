"""Parameters of the stress-blend model (one frozen pydantic model)."""

from __future__ import annotations

from pydantic import Field

from service.methods.params import MethodParams


class StressBlendParams(MethodParams):
    """Parameters of :func:`service.methods.stress_blend.model.train`."""


    stress_smoothing: int = Field(
        default=4, ge=0, le=200,
        description="Iterations of uniform Laplacian smoothing of the per-vertex stress "
                    "(the 'local' stress: averages over roughly this many rings, so the "
                    "weights vary smoothly over the surface).")
    power: float = Field(
        default=2.0, ge=2.0, le=16.0,
        description="Exponent p of the inverse-distance (Shepard) weights w_k ∝ 1/d_k^p of "
                    "the stress distances d_k to the scans; p = 2 makes the weights a "
                    "rational, infinitely differentiable function of the stress; larger p "
                    "sharpens the blend towards the nearest scan.")
    global_weight: float = Field(
        default=0.5, ge=0.0, le=100.0,
        description="β: weight of the whole frame's RMS stress distance to each scan, added "
                    "to the local distance (d_k² = local² + β² global²). It decides between "
                    "scans with the same local stress (skin an expression does not move) and "
                    "makes a frame equal to a scan reproduce it everywhere; 0: purely local.")
    regions: int = Field(
        default=8, ge=1, le=64,
        description="Wrinkle-map regions (masks) for real-time engines: per frame the engine "
                    "gets regions × expressions weights.")
    region_stress_scale_mm: float = Field(
        default=30.0, gt=0,
        description="Region clustering: mm of rest position that a saturated scan strain "
                    "(tanh(s / 0.05)) counts for (balances spatial compactness against "
                    "similar stress).")
    mask_smoothing: int = Field(
        default=6, ge=0, le=500,
        description="Iterations of uniform Laplacian smoothing that soften the region masks "
                    "(they stay a partition of unity).")
    seed: int = Field(default=0, description="Seed of the region clustering (k-means++).")
