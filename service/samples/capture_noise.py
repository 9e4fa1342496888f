"""Capture defects on clean marker tracks: seeded Gaussian noise and occlusion bursts.

Family-neutral (both sample actor families use it): it takes marker positions (F,M,3) in
any unit and returns perturbed copies, so every held-out performance can be written a
second and third time with the same ground-truth meshes and maps beside worse markers.

* **noise**: i.i.d. Gaussian, σ per coordinate (``MARKER_NOISE_MM`` = 0.3 mm, ordinary for
  optical mocap), so each marker's 3-D error has RMS ``√3 σ``;
* **occlusion bursts**: markers go missing (NaN in all three coordinates, the convention of
  :mod:`service.io.markers`) for *runs* of frames, as when a marker leaves a camera's view
  or a hand covers part of the face: single-marker dropouts (a Poisson number per marker,
  3–20 frames each) plus a few spatial clusters (the markers nearest a random marker,
  10–30 frames together). At most ``MAX_OCCLUDED_FRACTION`` of the markers are missing in
  any frame (bursts that would exceed it are cut).
"""

from __future__ import annotations

import zlib

import numpy as np

MARKER_NOISE_MM = 0.3            # σ per coordinate, mm
DROPOUTS_PER_MARKER_SECOND = 0.06
DROPOUT_FRAMES = (3, 20)
CLUSTERS_PER_SECOND = 0.25
CLUSTER_FRAMES = (10, 30)
CLUSTER_FRACTION = 0.12          # share of the markers a cluster covers
MAX_OCCLUDED_FRACTION = 0.35
VARIANTS = ("noisy", "occluded")


def variant_name(base: str, variant: str) -> str:
    """File stem of a marker variant of performance ``base``: ``<base>_<variant>``."""
    return f"{base}_{variant}"


def variant_salt(base: str) -> int:
    """A stable per-performance salt for the variants' generators (CRC-32 of the name)."""
    return zlib.crc32(base.encode())


def noisy_markers(markers: np.ndarray, sigma: float, rng: np.random.Generator) -> np.ndarray:
    """``markers + N(0, σ² I)`` (F,M,3), σ per coordinate in the markers' unit; NaN stays NaN."""
    X = np.asarray(markers, dtype=np.float64)
    return X + sigma * rng.standard_normal(X.shape)


def occlusion_mask(markers: np.ndarray, fps: float, rng: np.random.Generator) -> np.ndarray:
    """Occluded (F,M) bool: runs of frames per marker and clusters of nearby markers.

    Parameters
    ----------
    markers : (F,M,3) float   clean positions (the clusters are the markers nearest a random
                              one at its first frame)
    fps : float               frames per second (burst rates are per second)
    """
    X = np.asarray(markers, dtype=np.float64)
    F, M = X.shape[:2]
    seconds = F / fps
    frame = np.arange(F)
    mask = np.zeros((F, M), bool)
    # single-marker dropouts
    counts = rng.poisson(DROPOUTS_PER_MARKER_SECOND * seconds, size=M)
    owner = np.repeat(np.arange(M), counts)
    start = rng.integers(0, F, size=len(owner))
    length = rng.integers(DROPOUT_FRAMES[0], DROPOUT_FRAMES[1] + 1, size=len(owner))
    runs = (frame[None] >= start[:, None]) & (frame[None] < (start + length)[:, None])   # (b,F)
    np.logical_or.at(mask.T, owner, runs)
    # spatial clusters
    k = max(1, int(round(CLUSTER_FRACTION * M)))
    for _ in range(rng.poisson(CLUSTERS_PER_SECOND * seconds) + 1):
        centre = int(rng.integers(M))
        near = np.argsort(np.linalg.norm(X[0] - X[0, centre], axis=1))[:k]
        s = int(rng.integers(0, F))
        mask[s:s + int(rng.integers(CLUSTER_FRAMES[0], CLUSTER_FRAMES[1] + 1)), near[:, None]] = True
    # cap per frame: the markers of a frame beyond the cap (in marker order) stay visible
    cap = int(MAX_OCCLUDED_FRACTION * M)
    rank = np.cumsum(mask, axis=1)
    mask &= rank <= cap
    return mask


def occluded_markers(markers: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """Markers (F,M,3) with NaN where ``mask`` (F,M) is set."""
    X = np.array(markers, dtype=np.float64)
    X[np.asarray(mask, bool)] = np.nan
    return X


def marker_variants(markers: np.ndarray, fps: float, unit_scale: float, seed: int,
                    salt: int) -> dict[str, dict]:
    """The noisy and occluded versions of one performance's markers.

    Parameters
    ----------
    markers : (F,M,3) float   clean marker positions in the written unit
    unit_scale : float        written unit per mm (1 for mm, 0.1 for cm, 0.001 for m):
                              σ = ``MARKER_NOISE_MM · unit_scale``
    seed, salt : int          ``np.random.default_rng([seed, salt, 1 or 2])`` per variant

    Returns
    -------
    {"noisy": {"markers": (F,M,3), "info": {...}}, "occluded": {...}} (float32 markers;
    ``info`` is what the manifest records)
    """
    sigma = MARKER_NOISE_MM * unit_scale
    noisy = noisy_markers(markers, sigma, np.random.default_rng([seed, salt, 1]))
    mask = occlusion_mask(markers, fps, np.random.default_rng([seed, salt, 2]))
    return {
        "noisy": {"markers": noisy.astype(np.float32),
                  "info": {"variant": "noisy", "marker_noise_sigma": sigma,
                           "marker_noise_sigma_mm": MARKER_NOISE_MM}},
        "occluded": {"markers": occluded_markers(markers, mask).astype(np.float32),
                     "info": {"variant": "occluded",
                              "occluded_fraction": round(float(mask.mean()), 4)}},
    }


def variant_arrays(arrays: dict[str, np.ndarray], markers: np.ndarray) -> dict[str, np.ndarray]:
    """A performance's arrays with ``markers`` replaced and the clean ones kept as ``markers_clean``."""
    out = dict(arrays)
    out["markers_clean"] = arrays["markers"]
    out["markers"] = np.asarray(markers, np.float32)
    return out
