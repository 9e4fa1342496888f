"""Where a PDM's polynomial is valid, and what it becomes outside (issue 17, failure modes 1, 3).

ma2008 fits eq. 1 per texel to the (d1, d2) its training frames visited and is silent about
any other (d1, d2). A biquadratic there is not constrained by data: where a texel's
training parameters lie on a few rays from the neutral (one per training expression that
moves it), the quadratic form vanishing on those rays, ``(d·a⊥)(d·b⊥)``, is a null
direction of the fit that only the γ rows of §4.2 hold down, and it is largest exactly
between and beyond the rays, where an expression *combination* puts the texel.

Measured first (family a, level 0, biquadratic, ``heldout_combinations``): the worst
vertices (41 mm against the thin shell's 3.3 mm) have parameters *inside* the convex hull
of their training (d1, d2) (gauge 0.55–1.2) and within 10 % of the training radius of a
training sample; at one of them (vertex 5891) the training parameters lie on a ray
(d2/d1 ≈ 0.34), the frame's 9° off it, and the polynomial answers (1.4, 5.2, −6.3) mm
where its training values never exceed 2.9 mm: the off-ray null direction of the fit,
amplified by |d| ≈ 13. Neither a convex hull, nor an ellipse (the former limit, which
only clamps), nor a nearest-sample distance separates those points. So two guards:

1. **star-shaped validity region** per UV point: the radius function
   ``h_k = max_t r_t κ(θ_t − θ_k)`` over K angular sectors of the training parameters
   (r, θ polar; κ = 1 within one sector, 0 beyond ``REACH`` sectors), floored at ``HULL_FLOOR`` ×
   its maximum, so directions between trained rays (combinations) are outside. The gauge
   ``ρ(d) = r / h(θ)`` (h linear between sectors) is positively homogeneous: ``d_b = d / ρ``
   is the exit point of d's ray;
2. **training envelope** per point: ``E = max_t ‖D(d_t) − fallback‖`` over the training
   frames; the detail is limited to ``(1 + margin) E`` in norm;
3. **sector envelope** of the medium band (issue 17, failure mode 1, measured below): per
   UV point and sector, ``E_k = max_t ‖D(d_t) − fallback‖ κ(θ_t − θ_k)`` — the training
   detail in the direction of d, with the hull's angular kernel κ, linear between sectors
   — replaces E for the vertex band: ``E(θ) ≤ E``. One scalar E per point lets a
   combination keep the largest detail of *any* trained expression (a mouth corner's smile
   offset) in a direction where training only saw small detail;
4. **shell fallback and sector box** of the medium band (issue 17, "never worse than the
   thin shell"): the vertex band's fallback is, per frame, the *no detail* result itself —
   the thin shell of the detailed neutral ``V + B_det u_H``, as an offset in the base's
   frames (:func:`~service.methods.pdm.model.shell_fallback`) — and, per UV point, sector
   and channel, the detail ``D(d_t) − fallback_t`` is bounded by the box
   ``[min_t κ (D − fb)_t, max_t κ (D − fb)_t]`` of the training frames (0 included), the
   sector envelope's kernel, ``(1 + margin)`` × it applied per channel before the norm
   limit. The sector envelope is then measured against the same per-frame fallback.

   Measured first (family a, level 0, biquadratic; every frame of the held-out
   performances, face): the former fallback (the smooth neutral's thin shell plus the
   neutral's offset carried in its frames) is itself worse than the thin shell of the
   detailed neutral: max 6.33 / 8.95 / 10.98 mm against 5.19 / 7.31 / 8.40 (in range /
   combinations / out of range), worse on 153/154, 100/125 and 120/122 frames, the
   difference up to 3.5 mm at the lips (the two shells' bases differ there): no fade to it
   could meet the target. The worst PDM vertices (mouth corners, lips: 6643, 6417, 6056)
   lie *inside* their hulls (ρ 0.55–0.77, confidence 1) with the detail's norm within its
   sector envelope, but its direction opposite to what training showed in that sector
   (v6643, combinations frame 74: D = (3.3, 2.7, 4.8) mm where the nearest training frame,
   3.2 away in |d| ≤ 38, had (4.0, −1.1, −0.5)): the off-ray null direction of the fit, which a
   norm bound cannot see and the per-channel box does. Fallback alone: max 4.17 / 8.63 /
   9.12 mm (from 4.17 / 8.63 / 10.59); with the box: 4.17 / 7.18 / 8.81, mean 0.196 /
   0.317 / 0.253 → 0.194 / 0.307 / 0.242 mm (thin shell 0.266 / 0.396 / 0.501).

Then, with the method's safe *fallback* (for the medium PDM the thin shell of the detailed
neutral, 4.; 0 — the smooth neutral's shell with its static detail kept — where no per-frame
fallback is given; the constant term a5 for the fine and albedo PDMs: the
static neutral map)

    D̃(d) = fallback + w(ρ) · s · (L(d) − fallback),
    L(d) = D(d) for ρ ≤ 1,   Σ_k a_k m_k(d_b) (1 + slope · deg_k · (ρ − 1)) for ρ > 1,
    s = min(1, (1 + margin) E / ‖L(d) − fallback‖),
    w(ρ) = :func:`service.methods.confidence.falloff` (ρ − 1, width)   (1 at ρ ≤ 1, 0 at ρ ≥ 1 + width)

``L`` with ``slope = 1`` is the first-order Taylor expansion of D at d_b along the ray (by
Euler's theorem a monomial of degree k has ray derivative k·m_k): the polynomial continued
by a *linear* one; ``slope = 0`` holds the boundary's detail. D̃ equals D inside the region
wherever D stays within its envelope, and equals the fallback for ρ ≥ 1 + width. ``w`` is
also the point's confidence (:mod:`service.methods.confidence`).

The fine and albedo texels take ρ interpolated from the UV points (barycentric through the
UV triangle that covers them): the validity is a property of a region of the face, and a
per-texel region of a 1024² map would cost T × 1024² × K per model load. Everything is
derived from ``S_train`` when the model is trained and stored with it (:class:`ValidityData`;
a model stored without it derives it at load: about 9 s of a level-0 model's load, mostly
the fine band's envelope).

Measured for the sector envelope (family a, level 0, biquadratic, ``heldout_combinations``
frame 25, the worst vertex 6639 at the left mouth corner): d = (−27.7, −7.1) inside its
hull (ρ = 0.89), the out-of-plane part of its markers' S within the training's (0.44–0.78
of the training maximum: the 5D residual does not flag it either), PDM error 13.0 mm
against the thin shell's 4.3 mm. The cause there turned out to be the vertex band's
coefficients (sampled from the 512² map; fitted at the UV points since, see model.py), but
the sector envelope alone, on the sampled band, already moved family a's biquadratic
combinations (4 frames, clean) from max 12.99 → 11.87 mm and detail rel err 2.00 → 1.76
(in range unchanged: 0.272 → 0.275 mm mean, rel err 1.02).

Measured with the defaults (width 1, slope 1, margin 0.25) on family a's combinations
(13 frames, face): max vertex error 41.3 → 10.7 mm (thin shell 7.0), mean 0.47 → 0.36 mm
(thin shell 0.39); the benchmark tables are in ``benchmarks/generalization_report.py``'s
report.
"""

from __future__ import annotations

from typing import Callable, Iterable

import numpy as np

import dataclasses
import functools
from dataclasses import dataclass

import scipy.sparse as sp

from service.geometry.laplacian import triangle_areas
from service.geometry.uv_raster import interpolation_matrix, rasterize_uv
from service.methods.confidence import falloff, frame_confidence
from service.methods.footprint import UNREAD
from service.methods.pdm import polynomial

#: angular sectors of the star-shaped validity region
DIRECTIONS = 32
#: angular reach of a training sample, in sectors: its full radius up to one sector away
#: (so both sectors that bracket it hold it, and a training sample has ρ ≤ 1), falling
#: linearly to 0 at ``REACH`` sectors
REACH = 2.0
#: radius in a direction no training frame moved along, relative to the largest radius
HULL_FLOOR = 0.05
#: training samples within this fraction of a point's largest radius are at rest: their
#: detail bounds every sector of :func:`sector_envelope`
REST_RADIUS = 0.02
#: the detail may exceed its training envelope (and the medium band's sector box) by this
#: fraction before it is limited (the module docstring's ``margin``)
MARGIN = 0.25


def directions(K: int = DIRECTIONS) -> np.ndarray:
    """Angles θ_k (K,) = 2πk/K of the sectors."""
    return 2 * np.pi * np.arange(K) / K


def _kappa(angle: np.ndarray, theta: float, K: int, reach: float) -> np.ndarray:
    """The sectors' angular kernel κ (…) of samples at ``angle`` (…) for sector angle θ:
    1 within one sector, falling linearly to 0 at ``reach`` sectors."""
    delta = np.abs((angle - theta + np.pi) % (2 * np.pi) - np.pi)                  # in [0, π]
    return np.clip((reach - delta * K / (2 * np.pi)) / (reach - 1), 0.0, 1.0)


def training_hull(chunks: Callable[[], Iterable[tuple[np.ndarray, np.ndarray]]],
                  K: int = DIRECTIONS, reach: float = REACH, floor: float = HULL_FLOOR) -> np.ndarray:
    """Radius function (K,P) float32 of the training parameters (module docstring):
    ``h_k = max_t r_t κ(θ_t − θ_k)``, κ(Δ) = clip((reach − |Δ| K / 2π) / (reach − 1), 0, 1),
    floored.

    ``chunks()`` yields (d1, d2) pairs of (t,P) arrays covering all training frames.
    """
    theta = directions(K)
    h = np.zeros((K, 0))
    for d1, d2 in chunks():
        d1, d2 = np.asarray(d1, np.float64), np.asarray(d2, np.float64)
        r, a = np.hypot(d1, d2), np.arctan2(d2, d1)
        if h.shape[1] == 0:
            h = np.zeros((K, d1.shape[1]))
        for k, t in enumerate(theta):
            h[k] = np.maximum(h[k], (r * _kappa(a, t, K, reach)).max(axis=0))
    return np.maximum(h, floor * h.max(axis=0, keepdims=True) + 1e-12).astype(np.float32)


def gauge(d1: np.ndarray, d2: np.ndarray, hull: np.ndarray) -> np.ndarray:
    """ρ (…,P) = r / h(θ) of parameters d1, d2 (…,P) in the radius functions (K,P), h linear
    between the sectors: ≤ 1 inside, d/ρ on the boundary."""
    return point_gauge(d1, d2, np.ascontiguousarray(np.asarray(hull).T))


def point_gauge(d1: np.ndarray, d2: np.ndarray, hull_points: np.ndarray,
                lookup: "SectorLookup | None" = None) -> np.ndarray:
    """:func:`gauge` with the radius functions point-major, ``hull_points`` (P,K) (the
    transpose of the (K,P) hull, made once): a point's two bracketing sectors are then
    neighbours in memory, one flat gather instead of two column-strided ones (bit-identical).
    ``lookup``: :class:`SectorLookup` of the same d1, d2 (computed here when None)."""
    d1, d2 = np.broadcast_arrays(np.asarray(d1, np.float32), np.asarray(d2, np.float32))
    if lookup is None:
        lookup = SectorLookup.of(d1, d2, hull_points.shape[1])
    h = lookup.values(hull_points)
    return (np.hypot(d1, d2) / h).astype(np.float32)


@dataclass(frozen=True)
class SectorLookup:
    """Where the directions θ of parameters d1, d2 (…,P) fall among K sectors: the flat
    indices into a point-major (P,K) table of the sectors below and above θ, and the linear
    weight t of the upper one. Made once per frame and read for every per-sector table of
    the same points (the hull of :func:`point_gauge` and the sector envelope of
    :meth:`Validity.evaluate`: one direction computation instead of one per table).

    lower, upper : (…,P) int64;  t : (…,P) float32;  K : int the sectors
    """

    lower: np.ndarray
    upper: np.ndarray
    t: np.ndarray
    K: int

    @classmethod
    def of(cls, d1: np.ndarray, d2: np.ndarray, K: int) -> "SectorLookup":
        """The lookup of d1, d2 (…,P) (cast to float32) in K sectors."""
        d1, d2 = np.broadcast_arrays(np.asarray(d1, np.float32), np.asarray(d2, np.float32))
        x = (np.arctan2(d2, d1) % (2 * np.pi)) * (K / (2 * np.pi))
        k0 = np.floor(x).astype(np.int64) % K
        t = (x - np.floor(x)).astype(np.float32)
        base = np.arange(d1.shape[-1]) * K                                   # (P,) row starts
        upper = k0 + 1
        upper %= K
        upper += base
        k0 += base
        return cls(k0, upper, t, int(K))

    def values(self, table_points: np.ndarray) -> np.ndarray:
        """The table (P,K) at the looked-up directions, linear between sectors (…,P); a table
        of channels (P,K,…) (the sector box (P,K,2,3)) gives (…,P,…), the sectors found once
        for all C channels.

        A table of channels is read as one item of C values per (point, sector) (a void
        view of C·itemsize bytes): one gather of ``lower`` and one of ``upper`` move every
        channel at once, instead of gathering C scalars by the flat indices ``lower · C + c``
        (built per call). The same values, combined by the same float32 arithmetic, so
        bit for bit the flat gather (tests); on the level-1 sample actor's box (45,600 UV
        points × 32 sectors × 6) 5.2 → 1.7 ms of CPU per frame (load 6)."""
        if table_points.shape[1] != self.K:
            raise ValueError(f"a lookup in {self.K} sectors cannot read a table of {table_points.shape[1]}")
        table = np.ascontiguousarray(table_points)
        if table.ndim > 2:
            channels = table.shape[2:]
            C = int(np.prod(channels))
            items = table.reshape(-1, C).view(np.dtype((np.void, C * table.itemsize))).reshape(-1)
            lead = self.lower.shape
            t = self.t[..., None]
            lo = np.take(items, self.lower).view(table.dtype).reshape(*lead, C)
            hi = np.take(items, self.upper).view(table.dtype).reshape(*lead, C)
            out = (1 - t) * lo + t * hi
            return out.reshape(*lead, *channels)
        flat = table.ravel()
        return (1 - self.t) * np.take(flat, self.lower) + self.t * np.take(flat, self.upper)

    def sector_values(self, table_sectors: np.ndarray) -> np.ndarray:
        """:meth:`values` of a sector-major table (K,P,…) (the sector box's bounds as stored,
        (K,Q,3) each): the same values, gathered at ``k · P + p`` instead of ``p · K + k``."""
        K, P = table_sectors.shape[:2]
        if K != self.K:
            raise ValueError(f"a lookup in {self.K} sectors cannot read a table of {K}")
        p = np.arange(P)
        lookup = SectorLookup((self.lower - p * K) * P + p, (self.upper - p * K) * P + p, self.t, K)
        # the same memory seen as (P,K,…): item k·P + p is what the indices above name
        return lookup.values(np.ascontiguousarray(table_sectors).reshape(P, K, *table_sectors.shape[2:]))


def sector_envelope(coeffs: np.ndarray, chunks: Callable[[], Iterable[tuple[np.ndarray, ...]]],
                    fallback: np.ndarray | None, K: int = DIRECTIONS, reach: float = REACH,
                    box: bool = False) -> np.ndarray | tuple[np.ndarray, np.ndarray]:
    """Sector envelope (K,P) float32 (module docstring, 3.): ``E_k = max_t ‖D(d_t) −
    fallback_t‖ κ(θ_t − θ_k)`` of the band's polynomial (P,C,K') on its training parameters
    (chunks of (t,P) d1, d2), κ the kernel of :func:`training_hull`; ``fallback`` (P,C), or
    None when the chunks carry each frame's fallback as a third item (t,P,C) (the medium
    band's thin shell of the detailed neutral, module docstring 4.).
    Samples at rest (radius ≤ ``REST_RADIUS`` × the point's largest) count in every sector —
    at d → 0 the direction is undefined, so every sector holds at least the neutral's detail
    and the limit is continuous there. A sector no other training frame reached holds just
    that (beyond it the detail is limited towards the fallback).

    With ``box`` also the sector box (2,K,P,C) float32 (module docstring, 4.): per channel
    the smallest and largest ``κ (D(d_t) − fallback_t)`` (with 0: the fallback is always
    inside), returned as ``(envelope, box)``."""
    from service.methods.pdm.polynomial import evaluate

    a = np.asarray(coeffs, np.float32)
    theta = directions(K)
    env = np.zeros((K, len(a)), np.float32)
    lo_hi = np.zeros((2, K, len(a), a.shape[1]), np.float32) if box else None
    r_max = np.zeros(len(a))
    for d1, d2, *_ in chunks():                                   # the points' largest radius
        np.maximum(r_max, np.hypot(np.asarray(d1, np.float64), d2).max(axis=0), out=r_max)
    for d1, d2, *fb in chunks():
        d1, d2 = np.asarray(d1, np.float32), np.asarray(d2, np.float32)
        D = evaluate(a, d1, d2) - (fb[0] if fb else fallback)
        norm = np.sqrt(np.einsum("tpc,tpc->tp", D, D))
        ang = np.arctan2(d2.astype(np.float64), d1)
        rest = np.hypot(d1.astype(np.float64), d2) <= REST_RADIUS * r_max
        for k, t in enumerate(theta):
            kappa = _kappa(ang, t, K, reach)
            kappa[rest] = 1.0
            np.maximum(env[k], (norm * kappa).max(axis=0), out=env[k])
            if box:
                scaled = D * kappa[..., None].astype(np.float32)
                np.minimum(lo_hi[0, k], scaled.min(axis=0), out=lo_hi[0, k])
                np.maximum(lo_hi[1, k], scaled.max(axis=0), out=lo_hi[1, k])
    return (env, lo_hi) if box else env


def training_envelope(coeffs: np.ndarray, chunks: Callable[[], Iterable[tuple[np.ndarray, np.ndarray]]],
                      fallback: np.ndarray) -> np.ndarray:
    """Envelope (P,) float32: the largest ‖D(d_t) − fallback‖ (over channels) of the band's
    polynomial (P,C,K) on its training parameters (chunks of (t,P) d1, d2); ``fallback`` (P,C)."""
    from service.methods.pdm.polynomial import evaluate

    a = np.asarray(coeffs, np.float32)
    env = np.zeros(len(a), np.float32)
    for d1, d2 in chunks():
        D = evaluate(a, np.asarray(d1, np.float32), np.asarray(d2, np.float32)) - fallback
        np.maximum(env, np.sqrt(np.einsum("tpc,tpc->tp", D, D)).max(axis=0), out=env)
    return env


def valid_values(coeffs: np.ndarray, values: np.ndarray, d1: np.ndarray, d2: np.ndarray,
                 rho: np.ndarray, envelope: np.ndarray, fallback: np.ndarray, width: float,
                 slope: float, margin: float = MARGIN) -> np.ndarray:
    """D̃ (F,P,C) from ``values`` = D(d1, d2) (F,P,C) (module docstring): points of ρ > 1
    continued from the hull's boundary, every point's detail ``D − a5`` limited to
    ``(1 + margin)`` × its training ``envelope`` (P,) (or per frame (F,P): the sector
    envelope at d's direction) in norm, and faded by w(ρ) to the ``fallback`` (P,C). ``coeffs`` (P,C,K) of the band; d1, d2, rho (F,P). Modifies ``values``.

    Synthesis uses :func:`valid_polynomial` (the continuation inside the polynomial's own
    pass); this form takes the polynomial's values already evaluated."""
    outside = rho > 1
    if np.any(outside):
        continued = polynomial.evaluate(coeffs, d1, d2, rho, slope)
        np.copyto(values, continued, where=outside[..., None])
    return fade_detail(values, rho, envelope, fallback, width, margin)


def valid_polynomial(coeffs: np.ndarray, d1: np.ndarray, d2: np.ndarray, rho: np.ndarray,
                     envelope: np.ndarray, fallback: np.ndarray, width: float, slope: float,
                     margin: float = MARGIN, box: np.ndarray | None = None) -> np.ndarray:
    """D̃ (F,P,C) float32, C-contiguous, of the polynomial ``coeffs`` (P,C,K) at d1, d2 (F,P)
    with gauge ρ (F,P) (module docstring): the continued polynomial L
    (:func:`~service.methods.pdm.polynomial.evaluate` with ``rho``, D(d) bit for bit where
    ρ ≤ 1), then :func:`fade_detail` (``box``: its sector box at d's direction). Dense over
    the points: no gather of the points outside (but see :func:`valid_scalar_polynomial`,
    which one-channel bands take: the same values, the continuation and fade on the points
    that can change)."""
    if box is None and np.shape(coeffs)[1] == 1 and np.ndim(envelope) == 1 and np.ndim(fallback) == 2:
        return valid_scalar_polynomial(coeffs, d1, d2, rho, envelope, fallback, width, slope, margin)
    values = np.ascontiguousarray(polynomial.evaluate(coeffs, d1, d2, rho, slope))
    return fade_detail(values, rho, envelope, fallback, width, margin, box)


#: |detail| at most this fraction of (1 + margin) E is within the envelope whatever the
#: float32 rounding of its norm (``sqrt(fl(d²)) ≤ |d| (1 + 2⁻²³)``), with room
SURE_INSIDE = np.float32(1 - 2.0 ** -20)


def sure_bound(envelope: np.ndarray, margin: float = MARGIN) -> np.ndarray:
    """(P,) float32: ``SURE_INSIDE · (1 + margin) E`` where (1 + margin) E (float32, as
    :func:`fade_detail` forms it) is in [1e-18, 1e18], else −1 (no detail is surely
    inside): a one-channel detail ``|D − a5|`` at most this has w = 1 in the fade
    (:func:`valid_scalar_polynomial`)."""
    with np.errstate(over="ignore"):                  # an envelope near float32's largest
        bound = (1 + margin) * np.asarray(envelope, np.float32)
    ok = (bound >= np.float32(1e-18)) & (bound <= np.float32(1e18))
    return np.where(ok, bound * SURE_INSIDE, np.float32(-1)).astype(np.float32)


def valid_scalar_polynomial(coeffs: np.ndarray, d1: np.ndarray, d2: np.ndarray, rho: np.ndarray,
                            envelope: np.ndarray, fallback: np.ndarray, width: float, slope: float,
                            margin: float = MARGIN, sure: np.ndarray | None = None) -> np.ndarray:
    """:func:`valid_polynomial` (F,P,1) float32 of a one-channel band (coefficients (P,1,K),
    envelope (P,), fallback (P,1): the fine displacement), bit for bit, with the work done
    only where it can change a value (issue 23):

    * the plain polynomial everywhere; where some ρ > 1, the continued one (the dense
      pass's arithmetic, elementwise) on those points and on the inside points whose plain
      value is ±0 — the dense pass adds ``0 · Σ k a_k m_k`` to the inside points, which
      can turn a −0 into +0 and nothing else;
    * :func:`fade_detail` on the points that are outside or whose detail ``|D − a5|`` is
      not surely within ``(1 + margin) E`` (``sure``: :func:`sure_bound` of the envelope,
      made here when None): elsewhere the float32 norm is ≤ (1 + margin) E, w = 1, and
      the dense fade keeps the value.

    Measured on the level-1 sample actor's 715k fine texels (one in-range frame, 3.4 % of
    them outside, 4 % to fade), in blocks as synthesis runs it: 8.2 → 6.5 ms of CPU per
    frame (load 5.8; the plain polynomial is 2.5 of it)."""
    values = np.ascontiguousarray(polynomial.evaluate(coeffs, d1, d2))            # (F,P,1)
    dtype = values.dtype
    d1, d2, rho = np.broadcast_arrays(np.asarray(d1, dtype), np.asarray(d2, dtype), np.asarray(rho, dtype))
    P = d1.shape[-1]
    flat = values.reshape(-1)                                                     # (F·P,)
    outside = rho > 1
    if np.any(outside):
        idx = np.flatnonzero(outside | (flat == 0).reshape(outside.shape))
        p = idx % P
        flat[idx] = polynomial.evaluate(np.asarray(coeffs)[p], d1.reshape(-1)[idx], d2.reshape(-1)[idx],
                                        rho.reshape(-1)[idx], slope)[:, 0]
    const = np.ascontiguousarray(fallback, dtype=dtype)[:, 0]                     # (P,)
    sure = sure_bound(envelope, margin) if sure is None else sure
    detail = values.reshape(d1.shape) - const
    np.abs(detail, out=detail)
    fade = np.less_equal(detail, sure)
    np.logical_not(fade, out=fade)
    fade |= outside
    idx = np.flatnonzero(fade)
    if len(idx):
        p = idx % P
        flat[idx] = fade_detail(flat[idx].reshape(1, -1, 1), rho.reshape(-1)[idx][None],
                                np.asarray(envelope, dtype)[p][None], const[p][:, None], width, margin)[0, :, 0]
    return values


def fade_detail(values: np.ndarray, rho: np.ndarray, envelope: np.ndarray, fallback: np.ndarray,
                width: float, margin: float = MARGIN, box: np.ndarray | None = None) -> np.ndarray:
    """``fallback + w · (L − fallback)`` (F,P,C) of the continued values L (F,P,C), in place:
    ``w = min(1, (1 + margin) E / ‖L − fallback‖) · falloff(ρ − 1, width)`` (module
    docstring) with E the ``envelope`` (P,) or (F,P), fallback (P,C) or per frame (F,P,C),
    ρ (F,P). With ``box`` (2,F,P,C), the smallest and largest training detail at d's
    direction (:func:`sector_envelope`), ``L − fallback`` is first clipped per channel to
    ``(1 + margin)`` × that box (module docstring, 4.).

    float32 for float32 values: points of ρ ≤ 1 (falloff exactly 1) are the old gathered
    evaluation bit for bit; at ρ > 1 the falloff is evaluated in float32 (≤ 2 ulp of w).
    Points of w = 1 that the box does not clip keep their values unchanged (bit for bit)."""
    dtype = values.dtype
    const = np.ascontiguousarray(fallback, dtype=dtype)                         # (P,C) or (F,P,C)
    detail = values - const
    clipped = None
    if box is not None:
        bound = np.asarray(box, dtype) * dtype.type(1 + margin)
        inside = np.clip(detail, bound[0], bound[1])
        moved = inside != detail
        clipped = moved[..., 0].copy()                                         # (F,P): any channel
        for c in range(1, moved.shape[-1]):           # (np.any over a last axis of 3 is ~5x slower)
            clipped |= moved[..., c]
        detail = inside
    if detail.shape[-1] == 1:
        norm = detail[..., 0] * detail[..., 0]
        np.sqrt(norm, out=norm)
    else:
        norm = np.sqrt(np.einsum("fpc,fpc->fp", detail, detail))
    np.maximum(norm, 1e-30, out=norm)
    w = np.divide((1 + margin) * np.asarray(envelope, dtype), norm, out=norm)
    np.minimum(w, 1.0, out=w)
    outside = rho > 1
    if np.any(outside):
        w *= np.where(outside, falloff(np.asarray(rho, dtype) - dtype.type(1), width, dtype), dtype.type(1))
    fading = w < 1                                   # the others stay bit-identical to L
    if clipped is not None:
        fading |= clipped
    if np.any(fading):
        detail *= w[..., None]
        detail += const
        np.copyto(values, detail, where=fading[..., None])
    return values


@dataclass(frozen=True)
class ValidityData:
    """What the validity regions keep of the training data (stored with the model,
    ``validity.npz``; derived from the training S at load for models stored without it).

    hull : (D,Q) float32          radius function (:func:`training_hull`) at the Q UV points
    envelope : dict name → (P,)   training envelope (:func:`training_envelope`) of each
                                  evaluated band (``vertex``, ``fine``, ``albedo``), float32,
                                  in the stored band's point order (row-major texels)
    sectors : (D,Q) float32 or None   the medium band's sector envelope
                                  (:func:`sector_envelope`); None: stored before it existed
                                  (derived at load)
    sector_box : (2,D,Q,3) float32 or None   the medium band's sector box, relative to the
                                  thin shell of the detailed neutral (module docstring, 4.),
                                  as ``sectors`` then is; None: stored before (both derived
                                  at load, ``sectors`` having been relative to 0)
    """

    hull: np.ndarray
    envelope: dict
    sectors: np.ndarray | None = None
    sector_box: np.ndarray | None = dataclasses.field(default=None, metadata=UNREAD)   # (as Validity's)


@dataclass(frozen=True)
class Validity:
    """The validity regions of one PDM model and their use in synthesis (module docstring).

    hull_points : (Q,K) float32   radius function at the Q UV points of the medium PDM,
                                  point-major (:func:`point_gauge`; ``hull`` is the (K,Q) form)
    envelope : dict name → (P,)   the bands' training envelopes (:func:`training_envelope`)
    width, slope : float          the falloff's width in ρ − 1 and the continuation's order
    texel_rho : dict name → (P,Q) sparse   UV points → a texel band's points (barycentric)
    vertex_rho : (n,Q) sparse     UV points → vertices (seam mean)
    vertex_weight : (n,) float    vertex areas (the per-frame confidence's weights)
    sector_points : (Q,K) float32 or None   the medium band's sector envelope
                                  (:func:`sector_envelope`), point-major as ``hull_points``
                                  (``sectors`` is the (K,Q) form); None: the scalar envelope only
    sector_box : (2,K,Q,3) float32 or None   the medium band's sector box (lo, hi), relative
                                  to the per-frame fallback the vertex band is given, in the
                                  stored (:class:`ValidityData`) layout: sector-major, the
                                  array the store maps, no copy; what the NumPy operators
                                  read (synthesis reads :mod:`.point_validity`'s (K,Q,2,3)
                                  layout of it: the field is not weighed while mapped)
    """

    hull_points: np.ndarray
    envelope: dict
    width: float
    slope: float
    texel_rho: dict
    vertex_rho: sp.csr_matrix
    vertex_weight: np.ndarray
    sector_points: np.ndarray | None = None
    # synthesis reads the point validity's copy in its kernel's layout (.point_validity)
    sector_box: np.ndarray | None = dataclasses.field(default=None, metadata=UNREAD)
    sure: dict = dataclasses.field(default_factory=dict, compare=False, repr=False)   # name → sure_bound, made once
    compiled: dict = dataclasses.field(default_factory=dict, compare=False, repr=False)   # name → TexelValidity, made once

    @classmethod
    def build(cls, hull: np.ndarray, envelope: dict, width: float, slope: float, uv: np.ndarray,
              uv_faces: np.ndarray, seam_average: sp.csr_matrix, vertices: np.ndarray,
              faces: np.ndarray, bands: dict, sectors: np.ndarray | None = None,
              sector_box: np.ndarray | None = None, texel_rho: dict | None = None) -> "Validity":
        """``bands``: name → (resolution, index (P,)) of the texel bands that take ρ from the
        UV points; ``vertices`` (n,3), ``faces`` (m,3) the mesh whose areas weigh the frame;
        ``texel_rho``: name → the (P,K) CSR UV points → texels of a band, where already
        derived (a stored model's, :attr:`texel_rho`), instead of rasterizing the layout."""
        texel_rho = dict(texel_rho or {})
        for name, (H, index) in bands.items():
            if name not in texel_rho:
                raster = rasterize_uv(uv, uv_faces, H, H)
                texel_rho[name] = interpolation_matrix(raster, uv_faces, len(uv))[index].tocsr()
        area = np.bincount(np.asarray(faces).ravel(), np.repeat(triangle_areas(vertices, faces), 3),
                           minlength=len(vertices)) / 3
        return cls(np.ascontiguousarray(np.asarray(hull, np.float32).T), envelope, float(width), float(slope), texel_rho,
                   seam_average.tocsr(), area,
                   None if sectors is None else np.ascontiguousarray(np.asarray(sectors, np.float32).T),
                   None if sector_box is None else np.ascontiguousarray(sector_box, np.float32))

    def lookup(self, d1: np.ndarray, d2: np.ndarray) -> SectorLookup:
        """The :class:`SectorLookup` of parameters d1, d2 (F,Q) at the UV points, for
        :meth:`gauge` and :meth:`evaluate` of the same frame."""
        return SectorLookup.of(d1, d2, self.hull_points.shape[1])

    def gauge(self, d1: np.ndarray, d2: np.ndarray, lookup: SectorLookup | None = None) -> np.ndarray:
        """ρ (F,Q) at the UV points for their parameters d1, d2 (F,Q) (``lookup``: theirs,
        :meth:`lookup`, computed here when None)."""
        return point_gauge(d1, d2, self.hull_points, lookup)

    @property
    def hull(self) -> np.ndarray:
        """The radius functions (K,Q) float32 (:func:`training_hull`'s layout, as stored)."""
        return np.ascontiguousarray(self.hull_points.T)

    @property
    def sectors(self) -> np.ndarray | None:
        """The sector envelope (K,Q) float32 (:func:`sector_envelope`'s layout, as stored)."""
        return None if self.sector_points is None else np.ascontiguousarray(self.sector_points.T)

    def texels(self, name: str, rho: np.ndarray) -> np.ndarray:
        """ρ (F,P) of band ``name``'s points from ρ (F,Q) at the UV points
        (:func:`texel_gauge` of its operator)."""
        return texel_gauge(self.texel_rho[name], rho)

    def evaluate(self, name: str, coeffs: np.ndarray, d1: np.ndarray, d2: np.ndarray,
                 rho: np.ndarray, lookup: SectorLookup | None = None,
                 fallback: np.ndarray | None = None) -> np.ndarray:
        """D̃ (F,P,C) of band ``name`` (coefficients (P,C,K)) at d1, d2, ρ (F,P)
        (:func:`valid_polynomial`) towards ``fallback`` (F,P,C) (None: :meth:`fallback`); the
        vertex band with its sector envelope and sector box at d's direction, when there
        are (the box only with the per-frame fallback it was measured against), both read
        through one :class:`SectorLookup` (``lookup``: the :meth:`lookup` of d1, d2 if made)."""
        envelope, box = self.envelope[name], None
        if name == "vertex" and (self.sector_points is not None or self.sector_box is not None):
            if lookup is None:
                K = self.sector_points.shape[1] if self.sector_points is not None else self.sector_box.shape[1]
                lookup = SectorLookup.of(d1, d2, K)
            if self.sector_points is not None:
                envelope = lookup.values(self.sector_points)
            if self.sector_box is not None and fallback is not None:
                box = np.stack([lookup.sector_values(bound) for bound in self.sector_box])   # (2,F,Q,3)
        return valid_polynomial(coeffs, d1, d2, rho, envelope,
                                self.fallback(name, coeffs) if fallback is None else fallback,
                                self.width, self.slope, box=box)

    def prepare(self, name: str, coeffs: np.ndarray) -> None:
        """Make what :meth:`band` reads for texel band ``name`` (coefficients (P,C,K)) once:
        a one-channel band's :func:`sure_bound` and its compiled validity
        (:mod:`.texel_validity`; the padded ρ operator, 26 MB for the level-1 fine band), so
        a model pays for them when it is built, not at its first frame."""
        if coeffs.shape[1] != 1:
            return
        if name not in self.sure:
            self.sure[name] = sure_bound(self.envelope[name])
        R = self.texel_rho[name]
        if name not in self.compiled and name != "vertex" and R.dtype == np.float64 \
                and sp.isspmatrix_csr(R):                  # the fallback is a_last; float64 sums
            from service.methods.pdm.texel_validity import TexelValidity     # Numba: where synthesis runs

            self.compiled[name] = TexelValidity.build(R, np.asarray(coeffs).transpose(2, 1, 0), self.envelope[name],
                                                      self.sure[name], self.width, self.slope, MARGIN)

    def band(self, name: str, coeffs: np.ndarray, rho: np.ndarray) -> "BandValidity":
        """The validity of texel band ``name`` (coefficients (P,C,K)) for frames of ρ (F,Q)
        at the UV points (what :meth:`.texel_band.TexelBand.synthesize` applies per block);
        a one-channel band on the compiled kernels of :mod:`.texel_validity` (:meth:`prepare`)."""
        self.prepare(name, coeffs)
        return BandValidity(np.asarray(rho), self.texel_rho[name], coeffs, self.envelope[name],
                            self.fallback(name, coeffs), self.width, self.slope, self.sure.get(name),
                            self.compiled.get(name))

    @staticmethod
    def fallback(name: str, coeffs: np.ndarray) -> np.ndarray:
        """The static fallback (P,C) of band ``name``: 0 for the medium PDM (``vertex``: the
        smooth neutral's thin shell with the neutral's offset; synthesis passes the per-frame
        thin shell of the detailed neutral instead, module docstring 4.), the constant term
        a5 otherwise (the static neutral map)."""
        return np.zeros(coeffs.shape[:2], np.float32) if name == "vertex" else coeffs[:, :, -1]

    def confidence(self, rho: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Per-frame (F,) and per-vertex (F,n) float32 confidence of ρ (F,Q) at the UV points:
        the falloff weight w(ρ) (:mod:`service.methods.confidence`), seam-averaged to the
        vertices, and its area-weighted mean."""
        w = falloff(np.asarray(rho, np.float64) - 1, self.width)                 # (F,Q)
        cv = np.asarray(self.vertex_rho @ w.T).T                                # (F,n)
        return frame_confidence(cv, self.vertex_weight).astype(np.float32), cv.astype(np.float32)


def texel_gauge(R: sp.csr_matrix, rho: np.ndarray) -> np.ndarray:
    """ρ (F,P) float32 of a band's points from ρ (F,Q) at the UV points through its (P,Q)
    operator R: one sparse product per frame of its (Q,) row as float64 (SciPy's
    single-vector kernel; the (Q,F) product took the multi-vector one with the same sums in
    the same order, 3.6 → 2.6 ms for the 715k fine texels of the level-1 sample actor),
    rounded to float32."""
    rho = np.asarray(rho)
    dtype = np.result_type(R.dtype, rho.dtype)                        # SciPy's upcast
    out = np.empty((len(rho), R.shape[0]), np.float32)
    for f, row in enumerate(rho):
        out[f] = R @ np.asarray(row, dtype)
    return out


@dataclass(frozen=True)
class BandValidity:
    """The validity of one texel band for a few frames (:meth:`Validity.band`): ρ (F,Q) at
    the UV points, the band's operator to its points and what :func:`valid_values` needs,
    applied to any range of points (a block of :meth:`.texel_band.TexelBand.synthesize`,
    while its values are in the cache).

    point_rho : (F,Q);  texel_rho : (P,Q) CSR;  coeffs : (P,C,K);  envelope : (P,);  fallback : (P,C)
    sure : (P,) float32 or None   :func:`sure_bound` of the envelope (one-channel bands)
    compiled : TexelValidity or None   the one-channel band on compiled kernels
                                  (:mod:`.texel_validity`; :meth:`block` takes it)
    """

    point_rho: np.ndarray
    texel_rho: sp.csr_matrix
    coeffs: np.ndarray
    envelope: np.ndarray
    fallback: np.ndarray
    width: float
    slope: float
    sure: np.ndarray | None = None
    compiled: object = None

    @functools.cached_property
    def rho(self) -> np.ndarray:
        """ρ (F,P) float32 at the band's points (:func:`texel_gauge`, made on first use: the
        compiled :meth:`block` forms it per block instead)."""
        return texel_gauge(self.texel_rho, self.point_rho)

    @functools.cached_property
    def _point_rho64(self) -> np.ndarray:
        return np.ascontiguousarray(self.point_rho, np.float64)

    def block(self, d1: np.ndarray, d2: np.ndarray, s: int, e: int, out: np.ndarray) -> np.ndarray:
        """D̃ of points ``s:e`` at their d1, d2 (F,e−s) into ``out`` (F,e−s,C) float32, and the
        points outside (ρ > 1) per frame (F,) int: :meth:`evaluate` and :meth:`outside`, on
        the compiled kernels where there are (the same values bit for bit, tests)."""
        if self.compiled is not None and out.shape[-1] == 1:
            return self.compiled.evaluate(d1, d2, self._point_rho64, s, e, out[..., 0])
        out[...] = self.evaluate(d1, d2, s, e)
        return self.outside(s, e)

    def evaluate(self, d1: np.ndarray, d2: np.ndarray, s: int = 0, e: int | None = None) -> np.ndarray:
        """D̃ (F,e−s,C) of points ``s:e`` at their d1, d2 (F,e−s) (:func:`valid_polynomial`):
        elementwise per point, so any split into ranges gives the whole band's values bit
        for bit."""
        p = slice(s, e)
        if self.sure is not None:
            return valid_scalar_polynomial(self.coeffs[p], d1, d2, self.rho[:, p], self.envelope[p],
                                           self.fallback[p], self.width, self.slope, sure=self.sure[p])
        return valid_polynomial(self.coeffs[p], d1, d2, self.rho[:, p], self.envelope[p],
                                self.fallback[p], self.width, self.slope)

    def outside(self, s: int = 0, e: int | None = None) -> np.ndarray:
        """Points ``s:e`` outside their validity region (ρ > 1), counted per frame (F,) int."""
        return np.count_nonzero(self.rho[:, s:e] > 1, axis=-1)
