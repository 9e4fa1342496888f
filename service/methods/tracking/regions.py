"""The facial regions of the performance flow graph (fyffe, digital_ira_course2014, §4.1, Fig. 4e).

"We average the resulting confidence over twelve facial regions. These facial regions are
defined once on the neutral pose, and are warped to all other static poses using rough
static-to-static optical flow." Here the regions are a rows × cols grid (4 × 3 = 12 by
default: forehead, brows/eyes, nose/cheeks, mouth/chin, each left/centre/right) over the
bounding box of the face as the artist mesh projects into the neutral image; the paper's
are hand-drawn. Precise regions are not needed: they only select the graph's edges.
"""

from __future__ import annotations

import numpy as np

from service.geometry import optical_flow as of
from service.geometry.camera import Camera, rasterize


def face_regions(camera: Camera, V: np.ndarray, F: np.ndarray, face: np.ndarray | None = None,
                 rows: int = 4, cols: int = 3, scale: float = 1.0) -> np.ndarray:
    """Region labels (H,W) int of the neutral image: −1 off the face, else 0 … rows·cols − 1.

    Parameters
    ----------
    camera : the view the regions are drawn in (at full image size)
    V : (n,3) float   the artist mesh in its neutral pose (world, mm);  F : (m,3) int
    face : (n,) bool  vertices of the face (default all); a pixel is face when all three
                      corners of the triangle it sees are
    rows, cols : the grid;  scale : the label image's scale relative to the camera's images
    """
    cam = camera if scale == 1.0 else camera.scaled(scale)
    triangle, _ = rasterize(cam, V, F)
    fg = triangle >= 0
    if face is not None:
        fg[fg] = np.asarray(face, bool)[F[triangle[fg]]].all(axis=1)
    labels = np.full(triangle.shape, -1, np.int64)
    r, c = np.nonzero(fg)
    if len(r) == 0:
        return labels
    ri = np.minimum(((r - r.min()) * rows) // max(np.ptp(r) + 1, 1), rows - 1)
    ci = np.minimum(((c - c.min()) * cols) // max(np.ptp(c) + 1, 1), cols - 1)
    labels[r, c] = ri * cols + ci
    return labels


def carry_regions(labels: np.ndarray, flow: np.ndarray, mask: np.ndarray | None = None) -> np.ndarray:
    """The neutral's region labels carried to another image by a flow (nearest sampling).

    Parameters
    ----------
    labels : (H,W) int     labels on the neutral image (−1 off the face)
    flow : (H,W,2) float   backward flow with reference = the other image, moving = the
                           neutral image (``neutral(x + flow) ≈ other(x)``)
    mask : (H,W) bool      the other image's foreground (labels outside become −1)

    Returns
    -------
    labels : (H,W) int on the other image's grid
    """
    xy = np.rint(of.flow_to_coords(flow)).astype(np.int64)
    H, W = labels.shape
    inside = (xy[..., 0] >= 0) & (xy[..., 0] < W) & (xy[..., 1] >= 0) & (xy[..., 1] < H)
    out = np.full(labels.shape, -1, np.int64)
    out[inside] = labels[xy[..., 1][inside], xy[..., 0][inside]]
    if mask is not None:
        out[~np.asarray(mask, bool)] = -1
    return out


def region_means(confidence: np.ndarray, labels: np.ndarray, n_regions: int) -> np.ndarray:
    """Mean confidence (n_regions,) over each region's pixels (NaN for an empty region)."""
    sel = labels >= 0
    total = np.bincount(labels[sel], confidence[sel], minlength=n_regions)[:n_regions]
    count = np.bincount(labels[sel], minlength=n_regions)[:n_regions]
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(count > 0, total / np.maximum(count, 1), np.nan)
