"""The parameters of scan correspondence (Vuvuzela, digital_ira_course2014): a module of
their own so that the API validates a ``correspond`` job's parameters without importing the
method (and OpenCV, which its optical flow runs on)."""

from __future__ import annotations

from typing import Literal

from pydantic import Field

from service.methods.params import MethodParams


class CorrespondenceParams(MethodParams):
    """Parameters of :func:`~service.methods.correspondence.correspond.correspond` (the
    API's ``correspond`` job uses this same model).

    Defaults chosen on the level-1 sample actor's scans at 1024² (smile, brow raise, pucker;
    median / p95 warp error in texels): DIS to the finest scale, one pass, patch 8, stride 3,
    then 20 variational-refinement iterations: 0.093 / 0.36, 0.071 / 0.34, 0.065 / 0.41;
    without the refinement 0.074 / 0.35, 0.055 / 0.33, 0.049 / 0.43 (the refinement's
    smoothness blurs pore-level motion; α = 3 was worse, α = 30 about as good as none); a
    second (residual) pass 0.072 / 0.32, 0.055 / 0.31, 0.050 / 0.38; with sharpening gain 4
    and stride 2 as well, 0.070 / 0.29, 0.054 / 0.26 (the defaults). Patch 12 or 16 was
    worse at p95 (up to 1.9 texels on the pucker), the ``fast`` preset and σ = 2 or 6 of
    the sharpening about the same.
    """

    prewarp: bool = Field(True, description="step 1: Delaunay piecewise-affine pre-warp from "
                          "the landmarks (False: the flow starts from the identity)")
    flow: Literal["refined", "dis", "farneback", "none"] = Field(
        "refined", description="step 2: dense flow from the pre-warped source to the target. "
        "'refined' = DIS to the finest scale + residual DIS passes on the re-warped source "
        "(+ optional variational refinement); 'dis' and 'farneback' are plain OpenCV "
        "(default settings); 'none' keeps the pre-warp alone")
    sharpen_sigma: float = Field(3.0, ge=0.0, le=50.0, description="σ (texels) of the "
                                 "unsharp mask that over-sharpens the diffuse textures")
    sharpen_amount: float = Field(4.0, ge=0.0, le=20.0, description="gain of the unsharp "
                                  "mask's high-pass band (0: no sharpening)")
    dis_preset: Literal["ultrafast", "fast", "medium"] = Field("medium", description="DIS preset")
    dis_passes: int = Field(2, ge=1, le=5, description="DIS passes of the refined flow "
                            "(each on the re-warped source)")
    patch_size: int = Field(8, ge=4, le=32, description="DIS patch size, texels")
    patch_stride: int = Field(2, ge=1, le=16, description="DIS patch stride, texels")
    refinement_iterations: int = Field(0, ge=0, le=200, description="variational "
                                       "refinement iterations after the refined flow's passes "
                                       "(0: none; 20 raised the median error by ~30 % on the "
                                       "sample scans, see the class docstring)")
    smoothness: float = Field(10.0, gt=0.0, le=1000.0, description="smoothness weight α of "
                              "the variational refinement")
    pin_radius: float = Field(2.0, ge=0.5, le=20.0, description="radius (texels) of the black "
                              "dots pinned landmarks are rasterized into")
    confidence_window: float = Field(2.0, gt=0.0, le=20.0, description="σ (texels) of the NCC "
                                     "window of the confidence (fyffe §4.1)")
    confidence_smoothing: float = Field(4.0, ge=0.0, le=50.0, description="σ (texels) of the "
                                        "confidence's smoothing")
