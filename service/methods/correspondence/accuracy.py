"""Warp error of a correspondence against a known one (texels and mm).

The texel error of target texel x is ``‖coords(x) − truth(x)‖`` in source texels; the mm
error is the distance between the source surface points the two coordinates address,
``‖P_src(coords(x)) − P_src(truth(x))‖`` with P_src the source position map (bilinear).
"""

from __future__ import annotations

import numpy as np

from service.geometry import optical_flow as of


def warp_errors(coords: np.ndarray, truth: np.ndarray, valid: np.ndarray,
                source_position: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per-texel errors of a warp over the valid texels.

    Parameters
    ----------
    coords : (H,W,2) float   estimated source (column, row) of every target texel
    truth : (H,W,2) float    the known ones
    valid : (H,W) bool       texels scored
    source_position : (h,w,3) float   the source's position map, mm

    Returns
    -------
    texels : (k,) float64   errors in source texels, valid texels in row-major order
    mm : (k,) float64       the same in mm on the source surface
    """
    valid = np.asarray(valid, bool)
    d = np.asarray(coords, np.float64)[valid] - np.asarray(truth, np.float64)[valid]
    texels = np.linalg.norm(d, axis=1)
    p_est = of.sample(source_position, np.asarray(coords)[valid])
    p_true = of.sample(source_position, np.asarray(truth)[valid])
    mm = np.linalg.norm(p_est.astype(np.float64) - p_true, axis=1)
    return texels, mm


def summary(errors: np.ndarray) -> dict:
    """median, 95th percentile and mean of an error array."""
    e = np.asarray(errors, np.float64)
    return {"median": float(np.median(e)), "p95": float(np.percentile(e, 95)), "mean": float(e.mean())}
