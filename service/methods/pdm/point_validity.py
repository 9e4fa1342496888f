"""The medium band's validity at the UV points, compiled (issue 23).

Per frame the medium PDM's UV points (45,600 on the level-1 sample actor) go through the
validity of :mod:`.validity`: the sector of d's direction (:class:`.validity.SectorLookup`),
the gauge ρ in the radius functions (:func:`.validity.point_gauge`), the polynomial continued
past the hull (:func:`.polynomial.evaluate` with ρ), the sector envelope and sector box at
d's direction, the box's clip, the envelope's limit and the falloff towards the per-frame
shell fallback (:func:`.validity.fade_detail`). As NumPy passes that is about 20 passes
over (P,) and (P,3) float32 temporaries and four gathers of the point-major tables (under
cProfile 8.0 of an 18 ms mesh frame, load 4.6). Here it is two Numba kernels over point
ranges ``[lo, hi)`` (run by :func:`service.geometry.ranges.run`), each point read and
written once:

1. :func:`gauge_points`: the sector below d's direction and the weight of the one above,
   and ρ = |d| / h(θ) — what the confidence, the clamped fraction and the texel bands'
   validity read, so it is computed for every frame with validity;
2. :func:`valid_points`: D̃ (P,3) of the continued polynomial, clipped to the sector box,
   limited to the envelope and faded towards the fallback — only where a medium mesh is
   made (a mesh, a detailed mesh or a normal map is asked). The sector box is read
   sector-major with a point's lo and hi adjacent, (D,P,2,3): each point reads one 24-byte
   run in the sector below θ and one in the sector above (the stored (2,D,P,3), lo and hi
   in separate planes, read four: 3.30 → 2.64 ms per level-1 frame, the kernel alone,
   alternating in one process, load 8.7; point-major (P,D,2,3), 768 bytes between
   neighbouring points, 3.16; before that, 4.7 → 2.9 ms from point-major to the stored
   layout), the values bit for bit. A model's cache holds it in that layout
   (``op_point_box``, mapped); one stored before transposes the stored box at load.

The same float32 operations in the same order as the NumPy operators (compiled without
fast-math, so nothing is reassociated or contracted; NumPy's error model: IEEE division, no
zero test; the directions θ from NumPy's own arctan2), so the results are theirs bit for bit
(tests/methods/pdm/test_point_validity.py): a point inside its region whose detail is within
the envelope keeps the polynomial's value, as :func:`.validity.fade_detail` promises. The
NumPy operators stay as what the kernels are tested against (and
:meth:`.validity.Validity.evaluate` for any band). Numba is imported here, so this module is
imported where an evaluator is built, never by ``facesynth serve``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numba import njit, uint64

from service.geometry import ranges
from service.methods.pdm.polynomial import TERM_POWERS, _order_of
from service.methods.pdm.validity import MARGIN, Validity
from service.methods.pdm.validity_scalars import falloff, monomial

_TWO_PI = np.float32(2 * np.pi)


@njit(nogil=True, cache=True, error_model="numpy")
def gauge_points(lo, hi, d1, d2, theta, hull, rho, lower, t):
    """Points [lo, hi): of d = (d1, d2) (P,) float32 with direction ``theta`` (P,) float32
    (``np.arctan2(d2, d1)``: NumPy's float32 arctan2, which is not libm's — 39 % of random
    arguments differ by an ulp — so that the sectors are the NumPy gauge's bit for bit) the
    sector ``lower`` (P,) uint32 below θ among the D sectors of ``hull`` (P,D) float32, the
    weight ``t`` (P,) float32 of the sector above (``(θ mod 2π) D / 2π`` less its floor),
    and the gauge ``rho`` (P,) float32 = |d| / ((1 − t) h_lower + t h_upper)."""
    D = uint64(hull.shape[1])
    scale = np.float32(hull.shape[1] / (2 * np.pi))
    for p in range(uint64(lo), uint64(hi)):
        a, b = d1[p], d2[p]
        x = theta[p]
        if x < 0:
            x += _TWO_PI
        x *= scale
        f = np.floor(x)
        k0 = uint64(f) % D
        k1 = k0 + uint64(1)
        if k1 == D:
            k1 = uint64(0)
        w = x - f
        lower[p] = k0
        t[p] = w
        rho[p] = np.hypot(a, b) / ((np.float32(1) - w) * hull[p, k0] + w * hull[p, k1])


@njit(nogil=True, cache=True, error_model="numpy")
def valid_points(lo, hi, d1, d2, rho, lower, t, terms, pi, pj, envelope, sectors, box, fallback,
                 width, slope, grow, out):
    """Points [lo, hi): ``out`` (P,3) float32 = D̃(d) of the polynomial ``terms`` (K',3,P)
    (term k multiplies d1^pi[k] d2^pj[k]) at d = (d1, d2) with gauge ``rho`` and the sector
    (``lower``, ``t``) of :func:`gauge_points` (:mod:`.validity`'s module docstring):

    * L = Σ a_k m_k(d/ρ) (1 + slope deg_k (ρ − 1)) where ρ > 1, else D(d);
    * the detail L − fallback clipped per channel to ``(1 + margin)`` × the sector box
      ``box`` (D,P,2,3) (sector-major, a point's lo and hi adjacent) at θ, when it has
      sectors (D > 0),
      ``grow`` = 1 + margin (float32);
    * ``w = min(1, (1 + margin) E / |detail|) · falloff(ρ − 1, width)``, E the sector
      envelope ``sectors`` (P,D) at θ when it has sectors, else ``envelope`` (P,);
    * ``fallback + w · detail`` where w < 1 or the box clipped, else L unchanged."""
    D = uint64(sectors.shape[1])
    DB = uint64(box.shape[0])
    K = uint64(terms.shape[0])
    one = np.float32(1)
    for p in range(uint64(lo), uint64(hi)):
        r = rho[p]
        a, b = d1[p], d2[p]
        g = np.float32(0)
        outside = r > one
        if outside:
            a, b = a / r, b / r
            g = np.float32(slope) * (r - one)
        last = K - uint64(1)                       # the constant term, last (polynomial.TERM_POWERS)
        v0, v1, v2 = terms[last, 0, p], terms[last, 1, p], terms[last, 2, p]
        s0 = s1 = s2 = np.float32(0)
        for k in range(last):                      # polynomial.evaluate's order and roundings
            i, j = pi[k], pj[k]
            m = monomial(a, b, i, j)
            c0, c1, c2 = m * terms[k, 0, p], m * terms[k, 1, p], m * terms[k, 2, p]
            v0 += c0
            v1 += c1
            v2 += c2
            if outside:
                if i + j != 1:
                    deg = np.float32(i + j)
                    c0, c1, c2 = c0 * deg, c1 * deg, c2 * deg
                s0 += c0
                s1 += c1
                s2 += c2
        if outside:
            v0 += s0 * g
            v1 += s1 * g
            v2 += s2 * g
        f0, f1, f2 = fallback[p, 0], fallback[p, 1], fallback[p, 2]
        x0, x1, x2 = v0 - f0, v1 - f1, v2 - f2
        w = t[p]
        u = one - w
        k0 = uint64(lower[p])
        clipped = False
        if DB > 0:
            k1 = k0 + uint64(1)
            if k1 == DB:
                k1 = uint64(0)
            lo0 = (u * box[k0, p, 0, 0] + w * box[k1, p, 0, 0]) * grow
            lo1 = (u * box[k0, p, 0, 1] + w * box[k1, p, 0, 1]) * grow
            lo2 = (u * box[k0, p, 0, 2] + w * box[k1, p, 0, 2]) * grow
            hi0 = (u * box[k0, p, 1, 0] + w * box[k1, p, 1, 0]) * grow
            hi1 = (u * box[k0, p, 1, 1] + w * box[k1, p, 1, 1]) * grow
            hi2 = (u * box[k0, p, 1, 2] + w * box[k1, p, 1, 2]) * grow
            y0, y1, y2 = min(max(x0, lo0), hi0), min(max(x1, lo1), hi1), min(max(x2, lo2), hi2)
            clipped = y0 != x0 or y1 != x1 or y2 != x2
            x0, x1, x2 = y0, y1, y2
        if D > 0:
            k1 = k0 + uint64(1)
            if k1 == D:
                k1 = uint64(0)
            E = u * sectors[p, k0] + w * sectors[p, k1]
        else:
            E = envelope[p]
        norm = max(np.sqrt(x0 * x0 + x1 * x1 + x2 * x2), np.float32(1e-30))
        s = min(grow * E / norm, one)
        if outside:
            s *= falloff(r - one, width)
        if s < one or clipped:
            out[p, 0], out[p, 1], out[p, 2] = f0 + s * x0, f1 + s * x1, f2 + s * x2
        else:
            out[p, 0], out[p, 1], out[p, 2] = v0, v1, v2


@dataclass(frozen=True)
class PointValidity:
    """The medium band's validity at its P UV points as the kernels read it.

    hull : (P,D) float32          radius functions, point-major (:attr:`.validity.Validity.hull_points`)
    sectors : (P,D) or (P,0)      the sector envelope, point-major (none: ``envelope`` alone)
    envelope : (P,) float32       the training envelope (read where there are no sectors)
    box : (D,P,2,3) or (0,P,2,3)  the sector box, sector-major, each point's (lo, hi) adjacent
                                  (:attr:`.validity.Validity.sector_box` transposed, or the
                                  cache's copy, mapped; none: no clip)
    terms : (K',3,P) float32      the band's coefficients, term-major (:attr:`.texel_band.TexelBand.terms`)
    pi, pj : (K',) uint8          the powers of d1 and d2 of each term
    width, slope : float          the falloff's width and the continuation's order
    """

    hull: np.ndarray
    sectors: np.ndarray
    envelope: np.ndarray
    box: np.ndarray
    terms: np.ndarray
    pi: np.ndarray
    pj: np.ndarray
    width: float
    slope: float

    @classmethod
    def build(cls, validity: Validity, terms: np.ndarray, box: np.ndarray | None = None,
              values: bool = True) -> "PointValidity":
        """From the model's :class:`~.validity.Validity` and the vertex band's ``terms`` (K',3,P);
        ``box``: the sector box already in the kernel's layout (:meth:`point_box` of this
        validity, e.g. mapped from a model's cache), used when its shape is that layout's.
        ``values`` False: only :meth:`gauge` is read (a PDM whose mesh is the marker
        regression's never evaluates the medium band), so no sector box is held (35 MB at
        level 1, never paged in: issue 23's cache weight against the resident cost)."""
        P, D = validity.hull_points.shape
        sectors = validity.sector_points if validity.sector_points is not None else np.empty((P, 0), np.float32)
        stored = validity.sector_box
        want = (0 if stored is None else stored.shape[1], P, 2, 3)
        if not values:
            box = np.empty((0, P, 2, 3), np.float32)
        elif box is None or box.shape != want or box.dtype != np.float32 or not box.flags.c_contiguous:
            box = cls.point_box(validity)
        if sectors.shape[1] not in (0, D) or box.shape[0] not in (0, D):
            raise ValueError(f"the validity tables have {sectors.shape[1]} and {box.shape[0]} sectors, the hull {D}")
        powers = np.array(TERM_POWERS[_order_of(terms.shape[0])], np.uint8)
        f32 = lambda a: np.ascontiguousarray(a, np.float32)            # noqa: E731
        return cls(f32(validity.hull_points), f32(sectors), f32(validity.envelope["vertex"]), f32(box),
                   f32(terms), powers[:, 0].copy(), powers[:, 1].copy(), float(validity.width),
                   float(validity.slope))

    @staticmethod
    def point_box(validity: Validity) -> np.ndarray:
        """The sector box of ``validity`` (2,D,P,3) in the kernel's layout (D,P,2,3) float32
        (a copy; (0,P,2,3) without a box)."""
        P = validity.hull_points.shape[0]
        if validity.sector_box is None:
            return np.empty((0, P, 2, 3), np.float32)
        return np.ascontiguousarray(np.asarray(validity.sector_box, np.float32).transpose(1, 2, 0, 3))

    def gauge(self, d1: np.ndarray, d2: np.ndarray, threads: int | None = None
              ) -> tuple[np.ndarray, tuple[np.ndarray, np.ndarray]]:
        """ρ (F,P) float32 of parameters d1, d2 (F,P) and their sectors (lower (F,P) uint32,
        t (F,P) float32) for :meth:`values` (:func:`gauge_points`)."""
        d1, d2 = np.asarray(d1, np.float32), np.asarray(d2, np.float32)
        theta = np.arctan2(d2, d1)
        rho, t = np.empty(d1.shape, np.float32), np.empty(d1.shape, np.float32)
        lower = np.empty(d1.shape, np.uint32)
        for f in range(len(d1)):
            ranges.run(gauge_points, d1.shape[1], np.ascontiguousarray(d1[f]), np.ascontiguousarray(d2[f]),
                       theta[f], self.hull, rho[f], lower[f], t[f], threads=threads)
        return rho, (lower, t)

    def values(self, d1: np.ndarray, d2: np.ndarray, rho: np.ndarray, sectors: tuple,
               fallback: np.ndarray | None = None, threads: int | None = None) -> np.ndarray:
        """D̃ (F,P,3) float32 (:func:`valid_points`) at d1, d2, ρ (F,P) with the ``sectors`` of
        :meth:`gauge`, towards ``fallback`` (F,P,3) (None: 0, and the sector box unused: it
        was measured against the per-frame fallback)."""
        lower, t = sectors
        F, P = np.shape(d1)
        out = np.empty((F, P, 3), np.float32)
        box = self.box if fallback is not None else self.box[:0]
        for f in range(F):
            fb = np.zeros((P, 3), np.float32) if fallback is None else np.ascontiguousarray(fallback[f], np.float32)
            ranges.run(valid_points, P, np.ascontiguousarray(d1[f], np.float32), np.ascontiguousarray(d2[f], np.float32),
                       rho[f], lower[f], t[f], self.terms, self.pi, self.pj, self.envelope, self.sectors,
                       box, fb, self.width, self.slope, np.float32(1 + MARGIN), out[f], threads=threads)
        return out
