"""Unit mismatch between a request's markers and the actor they drive.

Markers sent in metres to a model trained in millimetres are 1000× too small; the model
would clamp every frame and answer a flat face with a ``clamped`` hint only. The check here
compares the markers' spread with the spread of the actor's marker layout on its neutral and
refuses a ratio outside :data:`SPREAD_BAND` with a 422 that names the likely unit.

Spread. The RMS distance of the markers from their centroid (the radius of gyration): it
does not change under rigid head motion, and it is computed over the markers visible in a
frame (NaN: occluded), compared with the layout's spread over the same markers. A request's
ratio is the median over its frames with at least :data:`MIN_VISIBLE` visible markers, so a
few bad frames do not decide it.

Band. Measured on the two sample actors (``facesynth sample-actor --seed 1``, levels 0 and
1; every frame of every performance, 1,028 frames each: the eight training clips, the
database and the two held-out performances): the per-frame ratio lies in [0.982, 1.049] at
level 0 and [0.981, 1.049] at level 1 (expressions move the markers by a few percent of the
face's size); with the left half of the markers occluded in every database frame, in
[0.979, 1.057]. Real faces open the jaw and stretch further than the sample rig, and
capture can lose a side of the face, so the band is far wider than measured: [1/3, 3], a
factor 3 either way. A unit error is a factor 10, 100 or 1000 (25.4 for inches), all outside.

The actor's unit. An actor's ``metadata.units`` (``m``, ``cm``, ``mm``, ...) names it when
given. Otherwise it is inferred from the size of a face: the layout's spread is 76.7 mm on
the sample actors, and a face's marker layout spreads 25–250 mm, a decade that only one of
m, cm and mm puts the layout in (:func:`face_unit`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Mapping

import numpy as np

from service.geometry.closest_point import surface_points
from service.methods.inputs import InvalidInput

#: accepted range of (markers' spread) / (layout's spread); see the module docstring
SPREAD_BAND = (1 / 3, 3.0)
#: frames with fewer visible markers are not measured
MIN_VISIBLE = 3
#: length units by their size in metres, for naming the likely unit
UNITS: Mapping[str, float] = {"m": 1.0, "dm": 0.1, "cm": 0.01, "mm": 0.001, "in": 0.0254}
_UNIT_NAMES = {"m": "metres", "dm": "decimetres", "cm": "centimetres", "mm": "millimetres",
               "in": "inches"}


#: a face's marker-layout spread, metres (the sample actors': 0.0767)
FACE_SPREAD_M = (0.025, 0.25)


@dataclass(frozen=True)
class MarkerReference:
    """An actor's marker layout on its neutral, for checking the units of requests.

    Attributes
    ----------
    rest : (M,3) float   the layout's markers on the neutral, actor's unit
    unit : str or None   the actor's unit (a key of :data:`UNITS`), if known or inferred
    """

    rest: np.ndarray
    unit: str | None

    def check(self, frames: np.ndarray, what: str = "the markers") -> None:
        """:func:`check_marker_units` of ``frames`` against this layout."""
        check_marker_units(frames, self.rest, self.unit, what)


def face_unit(rest: np.ndarray, declared: object = None) -> str | None:
    """The actor's length unit: ``declared`` if it is one of :data:`UNITS`, else the one of
    m, cm, mm that makes the layout's spread a face's (:data:`FACE_SPREAD_M`), else None."""
    if isinstance(declared, str) and declared in UNITS:
        return declared
    spread = rms_spread(rest)
    fits = [u for u in ("m", "cm", "mm") if FACE_SPREAD_M[0] <= spread * UNITS[u] < FACE_SPREAD_M[1]]
    return fits[0] if len(fits) == 1 else None


def layout_positions(V: np.ndarray, F: np.ndarray, triangle: np.ndarray,
                     barycentric: np.ndarray) -> np.ndarray:
    """The layout's markers on the neutral, (M,3) in the actor's unit.

    Parameters
    ----------
    V : (n,3) float   neutral vertices
    F : (m,3) int     neutral triangles
    triangle : (M,) int, barycentric : (M,3) float   the canonical layout
    """
    return surface_points(np.asarray(V, np.float64), np.asarray(F), np.asarray(triangle),
                          np.asarray(barycentric, np.float64))


def spread_ratios(frames: np.ndarray, rest: np.ndarray) -> np.ndarray:
    """Per frame, the markers' spread over the layout's spread on the same visible markers.

    Parameters
    ----------
    frames : (F,M,3) float   marker positions, NaN where occluded
    rest : (M,3) float       the layout's markers on the neutral

    Returns
    -------
    (F',) float   the ratios of the frames with at least :data:`MIN_VISIBLE` visible markers
                  (and a non-zero layout spread over them)
    """
    X = np.asarray(frames, np.float64)
    R = np.asarray(rest, np.float64)
    visible = np.isfinite(X).all(axis=2)                           # (F,M)
    if visible.all():                  # every marker visible: no masks (a per-frame request)
        ms_r = rms_spread(R) ** 2
        if len(R) < MIN_VISIBLE or ms_r <= 0:
            return np.zeros(0)
        Xc = X - X.mean(axis=1, keepdims=True)
        return np.sqrt(np.einsum("fmk,fmk->f", Xc, Xc) / (len(R) * ms_r))
    W = visible.astype(np.float64)
    n = W.sum(axis=1)
    keep = n >= MIN_VISIBLE
    W, n, X = W[keep], n[keep], np.nan_to_num(X[keep])
    # mean squared distance from the centroid = E|x|² - |E x|², per frame over visible markers
    mx = W[:, :, None] * X
    ms_x = np.einsum("fm,fm->f", W, np.einsum("fmk,fmk->fm", X, X)) / n \
        - np.einsum("fk,fk->f", mx.sum(1), mx.sum(1)) / n**2
    c_r = W @ R / n[:, None]
    ms_r = W @ np.einsum("mk,mk->m", R, R) / n - np.einsum("fk,fk->f", c_r, c_r)
    ok = ms_r > 0
    return np.sqrt(np.maximum(ms_x[ok], 0) / ms_r[ok])


def rms_spread(points: np.ndarray) -> float:
    """RMS distance of (M,3) points from their centroid, ignoring NaN rows."""
    P = np.asarray(points, np.float64)
    P = P[np.isfinite(P).all(axis=1)]
    return float(np.sqrt(np.mean(np.sum((P - P.mean(axis=0)) ** 2, axis=1)))) if len(P) else 0.0


def check_marker_units(frames: np.ndarray, rest: np.ndarray, unit: str | None = None,
                       what: str = "the markers") -> None:
    """Refuse markers whose spread is off the layout's by more than :data:`SPREAD_BAND`.

    Parameters
    ----------
    frames : (F,M,3) float   the request's markers, NaN where occluded
    rest : (M,3) float       the layout's markers on the actor's neutral
    unit : str, optional     the actor's length unit (a key of :data:`UNITS`), for naming
                             the unit the markers were likely sent in
    what : str               the frames' name in the message

    Raises
    ------
    InvalidInput   e.g. "the markers span 0.0874 units (RMS distance from their centroid),
                   the actor's marker layout spans 87.4 mm: about 1000× smaller; were they
                   sent in metres? Send markers in the actor's unit (mm)."
    """
    ratios = spread_ratios(frames, rest)
    if len(ratios) == 0:
        return
    ratio = float(ratios[0] if len(ratios) == 1 else np.median(ratios))
    low, high = SPREAD_BAND
    if low <= ratio <= high or ratio == 0:
        return
    reference = rms_spread(rest)
    sent = ratio * reference
    unit_text = unit or "units"
    factor = 1 / ratio if ratio < 1 else ratio              # > 3 outside the band
    direction = "smaller" if ratio < 1 else "larger"
    guess = _likely_unit(ratio, unit)
    question = f"; were they sent in {guess}?" if guess else ""
    raise InvalidInput(
        f"{what} span {sent:.3g} units (RMS distance from their centroid, median over "
        f"{len(ratios)} frame(s)), the actor's marker layout spans {reference:.3g} "
        f"{unit_text}: about {_sig3(factor):g}× {direction}{question} Send markers in the "
        f"actor's unit{f' ({unit})' if unit else ''}, as its clips were; the spreads may "
        f"differ by a factor {SPREAD_BAND[1]:g} at most.")


def _sig3(value: float) -> float:
    """``value`` rounded to 3 significant digits (1002.4 → 1000.0, 5.004 → 5.0)."""
    return round(value, 2 - int(math.floor(math.log10(value))))


def _likely_unit(ratio: float, unit: str | None) -> str | None:
    """The unit whose size relative to the actor's explains ``ratio`` within 15 %, or a
    power of ten when the actor's unit is unknown."""
    if unit in UNITS:
        size = UNITS[unit] / ratio                       # the sent unit's size in metres
        best = min(UNITS, key=lambda u: abs(math.log(UNITS[u] / size)))
        if abs(math.log(UNITS[best] / size)) < math.log(1.15) and best != unit:
            return _UNIT_NAMES[best]
        return None
    power = round(math.log10(ratio))
    if power != 0 and abs(math.log10(ratio) - power) < math.log10(1.15):
        return f"units {10 ** abs(power)}× {'larger' if power < 0 else 'smaller'} than the actor's"
    return None
