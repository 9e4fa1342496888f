"""The image the flow sees: the over-sharpened diffuse texture with masks and pinned dots.

digital_ira_course2014, "Vuvuzela: A Facial Scan Correspondence Tool": all correspondence
processing uses the diffuse textures only; there is "plenty of naturally occurring texture
in the face, especially when over-sharpened"; for hard cases "we paint black masks around
occlusion regions in both source and target diffuse textures" and "we mark some points as
'pinned' and those points are rasterized into small black dots at runtime".

Over-sharpening is an unsharp mask of the luminance, ``L + k (L − G_σ * L)``; the Gaussian
is a normalized convolution over the covered texels, so the chart border does not ring.
"""

from __future__ import annotations

import numpy as np

from service.geometry.optical_flow import gaussian_blur

#: Rec. 709 luminance weights of linear RGB
LUMA = np.array([0.2126, 0.7152, 0.0722])


def luminance(image: np.ndarray) -> np.ndarray:
    """(H,W) luminance of a linear-RGB (H,W,3) image; a single-channel (H,W) one unchanged."""
    img = np.asarray(image, dtype=np.float64)
    if img.ndim == 2:
        return img
    if img.ndim == 3 and img.shape[2] == 1:
        return img[..., 0]
    if img.ndim == 3 and img.shape[2] >= 3:
        return img[..., :3] @ LUMA
    raise ValueError(f"expected an (H,W) or (H,W,3) image, got {img.shape}")


def oversharpen(image: np.ndarray, mask: np.ndarray, sigma: float, amount: float) -> np.ndarray:
    """Unsharp mask ``L + amount (L − G_σ * L)`` over the covered texels; 0 outside.

    Parameters
    ----------
    image : (H,W) float   luminance
    mask : (H,W) bool     covered texels
    sigma : float         σ of the Gaussian, texels (0: no sharpening)
    amount : float        gain k of the high-pass band

    Returns
    -------
    sharp : (H,W) float64
    """
    L = np.where(mask, np.nan_to_num(np.asarray(image, dtype=np.float64)), 0.0)
    if sigma <= 0 or amount == 0:
        return L
    m = mask.astype(np.float32)
    blur = gaussian_blur(L, sigma) / np.maximum(gaussian_blur(m, sigma), 1e-12)
    return np.where(mask, L + amount * (L - blur), 0.0)


def flow_texture(albedo: np.ndarray, mask: np.ndarray, sigma: float, amount: float,
                 occlusion: np.ndarray | None = None, pinned_xy: np.ndarray | None = None,
                 pin_radius: float = 2.0) -> np.ndarray:
    """The flow's input image of one scan: over-sharpened luminance, masks and pins black.

    Parameters
    ----------
    albedo : (H,W,3) or (H,W) float   diffuse albedo
    mask : (H,W) bool                 covered texels
    sigma, amount : float             :func:`oversharpen`
    occlusion : (H,W) bool | None     painted occlusion mask (black)
    pinned_xy : (P,2) float | None    pinned points, texel (column, row): black dots
    pin_radius : float                dot radius, texels

    Returns
    -------
    texture : (H,W) float64   0 ("black") outside the mask, in occlusions and in the dots
    """
    mask = np.asarray(mask, bool)
    tex = oversharpen(luminance(albedo), mask, sigma, amount)
    black = ~mask
    if occlusion is not None:
        black |= np.asarray(occlusion, bool)
    if pinned_xy is not None and len(pinned_xy):
        black |= pin_dots(pinned_xy, mask.shape, pin_radius)
    tex[black] = 0.0
    return tex


def pin_dots(xy: np.ndarray, shape: tuple[int, int], radius: float) -> np.ndarray:
    """(H,W) bool: discs of ``radius`` texels around points xy (P,2) (column, row)."""
    H, W = shape
    out = np.zeros((H, W), bool)
    r = int(np.ceil(radius))
    dy, dx = np.mgrid[-r:r + 1, -r:r + 1]
    disc = dx ** 2 + dy ** 2 <= radius ** 2
    cx = np.rint(np.asarray(xy)[:, 0]).astype(np.int64)[:, None] + dx[disc][None]
    cy = np.rint(np.asarray(xy)[:, 1]).astype(np.int64)[:, None] + dy[disc][None]
    keep = (cx >= 0) & (cx < W) & (cy >= 0) & (cy < H)
    out[cy[keep], cx[keep]] = True
    return out
