"""A one-channel texel band's validity, compiled (issue 23): the fine PDM's per-frame pass.

Per frame the fine PDM's texels (715k on the level-1 sample actor, 1024²) take the gauge ρ
from the UV points (:meth:`.validity.Validity.texels`: a sparse product in float64), the
polynomial of eq. 1 (:func:`.polynomial.evaluate`) and, where a value can change, the
continuation past the hull and the fade to the static neutral map
(:func:`.validity.valid_scalar_polynomial`). As NumPy passes that is a CSR product per
frame, one pass per term over the block's points and about ten passes over the block for
the continuation's and the fade's selections (under cProfile about 9 of a 47 ms maps
frame). Here, per block of points (:meth:`.texel_band.TexelBand.synthesize`'s blocks):

1. :func:`texel_gauge`: ρ of each texel (its ≤ 3 UV points' ρ, in float64 as SciPy's
   ``csr_matvec`` sums a row, rounded to float32) and the count of points outside (ρ > 1);
2. :func:`polynomial_flags`: the plain polynomial, one straight-line loop per polynomial
   order that LLVM vectorizes (no branch, contiguous float32 rows), and a flag per point
   where the continuation or the fade can change its value (``valid_scalar_polynomial``'s
   selections: ρ > 1, a ±0 value when some point of the block is outside, a detail not
   surely within the envelope);
3. :func:`repair`: the flagged points (``np.flatnonzero``: a few percent), continued and
   faded with that function's float32 operations in its order.

The same operations in the same order as the NumPy operators (compiled without fast-math:
nothing reassociated or contracted; NumPy's error model), so the values, their zeros' signs
and NaNs are theirs bit for bit (tests/methods/pdm/test_texel_validity.py). Rows of the ρ
operator with fewer than 3 entries are padded with weight 0 on an entry of the row: adding
``+0 · ρ`` to a sum of non-negative products that starts from +0 changes nothing for finite
ρ (ρ = |d| / h, h > 0, is finite for finite d). The padded arrays (3,P) uint32 and float64
are a copy of the operator (26 MB for the level-1 fine band, made when the model is built,
:meth:`.validity.Validity.prepare`, by :func:`padded_rows`): reading the CSR rows directly (SciPy's loop, no copy) measured 2.8 → 9.4 ms per
frame (alternating in one process, load 8). Numba is imported here, so this module is
imported where an evaluator is built, never by ``facesynth serve``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
from numba import njit, uint64

from service.methods.pdm.validity_scalars import falloff, monomial
from service.methods.pdm.polynomial import TERM_POWERS, _order_of

#: entries per row of the ρ operator (UV points → texels: a texel's triangle corners)
CORNERS = 3


@njit(nogil=True, cache=True, error_model="numpy")
def padded_rows(indptr, indices, data, corner, weight):
    """The CSR rows (``indptr`` (P+1,), ``indices``, ``data``; at most :data:`CORNERS`
    entries a row) into ``corner`` (3,P) uint32 and ``weight`` (3,P) float64, each row's
    entries in order, padded with weight 0 on the row's first entry (0 for an empty row).
    One pass over the rows: 3 ms for the level-1 fine band, where the NumPy scatter it
    replaces (``np.repeat`` of the rows and slots, two fancy assignments) took 0.10–0.19 s
    of the model's load."""
    for p in range(corner.shape[1]):
        s, e = indptr[p], indptr[p + 1]
        first = indices[s] if e > s else 0
        for c in range(CORNERS):
            if s + c < e:
                corner[c, p] = indices[s + c]
                weight[c, p] = data[s + c]
            else:
                corner[c, p] = first
                weight[c, p] = 0.0


@njit(nogil=True, cache=True, error_model="numpy", inline="always")
def _rho(p, point_rho, corner, weight):
    """ρ of point p: ``0 + w0 ρ_0 + w1 ρ_1 + w2 ρ_2`` in float64 (SciPy's CSR row sum), rounded."""
    r = np.float64(0) + weight[0, p] * point_rho[corner[0, p]]
    r += weight[1, p] * point_rho[corner[1, p]]
    r += weight[2, p] * point_rho[corner[2, p]]
    return np.float32(r)


@njit(nogil=True, cache=True, error_model="numpy")
def texel_gauge(lo, hi, point_rho, corner, weight, rho):
    """The band's points [lo, hi): ρ into ``rho`` (hi−lo,) float32, from the UV points' ρ
    (Q,) float64 through the padded operator ``corner`` (3,P) uint32, ``weight`` (3,P)
    float64; returns how many have ρ > 1. (A scalar loop: LLVM does not vectorize the
    float64 gathers.)"""
    count = 0
    for q in range(uint64(hi) - uint64(lo)):
        r = _rho(q + uint64(lo), point_rho, corner, weight)
        rho[q] = r
        count += r > 1
    return count


@njit(nogil=True, cache=True, error_model="numpy", inline="always")
def _needs_repair(v, r, const, sure, continued):
    """Whether :func:`repair` can change the plain value v of a point with ρ r: outside
    (ρ > 1), a ±0 the continuation may re-sign (``continued``), or a detail ``|v − a_last|``
    not surely within the envelope (``valid_scalar_polynomial``'s selections)."""
    return (r > 1) | (continued & (v == 0)) | ~(abs(v - const) <= sure)


@njit(nogil=True, cache=True, error_model="numpy")
def polynomial_flags(lo, hi, d1, d2, rho, terms, sure, continued, out, flag):
    """The band's points [lo, hi): the plain polynomial of ``terms`` (K,1,P) float32 at their
    d1, d2 (hi−lo,) float32 into ``out`` (hi−lo,), and ``flag`` (hi−lo,) bool the points
    :func:`repair` must see (ρ ``rho`` (hi−lo,), the sure bound ``sure`` (P,), ``continued``:
    some point of the block is outside). One straight-line loop per order (K = 3, 6, 10
    terms of :data:`.polynomial.TERM_POWERS`), vectorized: ``v = a_last; v += m_k a_k`` in
    :func:`.polynomial.evaluate`'s order and roundings (powers as repeated products)."""
    n = uint64(hi) - uint64(lo)
    K = terms.shape[0]
    if K == 6:                                              # biquadratic (ma2008 eq. 1)
        for q in range(n):
            p = q + uint64(lo)
            a, b = d1[q], d2[q]
            c = terms[5, 0, p]
            v = c
            v += (a * a) * terms[0, 0, p]
            v += (b * b) * terms[1, 0, p]
            v += (a * b) * terms[2, 0, p]
            v += a * terms[3, 0, p]
            v += b * terms[4, 0, p]
            out[q] = v
            flag[q] = _needs_repair(v, rho[q], c, sure[p], continued)
    elif K == 3:                                            # linear
        for q in range(n):
            p = q + uint64(lo)
            a, b = d1[q], d2[q]
            c = terms[2, 0, p]
            v = c
            v += a * terms[0, 0, p]
            v += b * terms[1, 0, p]
            out[q] = v
            flag[q] = _needs_repair(v, rho[q], c, sure[p], continued)
    else:                                                   # bicubic
        for q in range(n):
            p = q + uint64(lo)
            a, b = d1[q], d2[q]
            a2, b2 = a * a, b * b
            c = terms[9, 0, p]
            v = c
            v += (a2 * a) * terms[0, 0, p]
            v += (b2 * b) * terms[1, 0, p]
            v += (a2 * b) * terms[2, 0, p]
            v += (a * b2) * terms[3, 0, p]
            v += a2 * terms[4, 0, p]
            v += b2 * terms[5, 0, p]
            v += (a * b) * terms[6, 0, p]
            v += a * terms[7, 0, p]
            v += b * terms[8, 0, p]
            out[q] = v
            flag[q] = _needs_repair(v, rho[q], c, sure[p], continued)


@njit(nogil=True, cache=True, error_model="numpy")
def repair(lo, points, d1, d2, rho, terms, pi, pj, envelope, width, slope, grow, continued, out):
    """The flagged points of the block starting at the band's point ``lo``, ``points`` (k,)
    int64 into the block's ``out`` (n,) float32 (the plain polynomial of ``terms`` (K,1,P)
    at d1, d2 (n,) with ρ (n,) float32): ``valid_scalar_polynomial``'s continuation (ρ > 1,
    and ±0 values when ``continued``: some point of the block is outside) and its fade
    (ρ > 1 or ``|v − a_last|`` not ≤ the sure bound), with the training ``envelope`` (P,)
    float32, the falloff ``width``, the continuation ``slope`` and ``grow`` = 1 + its
    ``margin`` (float32), in that function's float32 operations and order."""
    one = np.float32(1)
    last = terms.shape[0] - 1
    for q in points:
        p = uint64(q) + uint64(lo)
        v = out[q]
        r = rho[q]
        outside = r > one
        const = terms[last, 0, p]
        if continued and (outside or v == 0):     # polynomial.evaluate with ρ, one point
            rr = r if (r > one or r != r) else one
            a, b = d1[q] / rr, d2[q] / rr
            g = (rr - one) * slope
            v = const
            s = np.float32(0)
            for k in range(last):
                i, j = pi[k], pj[k]
                c = monomial(a, b, i, j) * terms[k, 0, p]
                v += c
                if i + j != 1:
                    c *= np.float32(i + j)
                s += c
            s *= g
            v += s
            out[q] = v
        detail = v - const                        # validity.fade_detail, one channel
        norm = np.sqrt(detail * detail)
        norm = norm if (norm > np.float32(1e-30) or norm != norm) else np.float32(1e-30)
        w = grow * envelope[p] / norm
        w = w if (w < one or w != w) else one
        if outside:
            w *= falloff(r - one, width)
        if w < one:
            out[q] = detail * w + const


@dataclass(frozen=True)
class TexelValidity:
    """The compiled validity of a one-channel texel band (module docstring), built once per
    band by :meth:`build` and applied per block by :meth:`evaluate`.

    corner : (3,P) uint32, weight : (3,P) float64   the ρ operator (UV points → the band's
                                  points), padded to 3 entries a row
    terms : (K,1,P) float32       the band's coefficients, term-major (:attr:`.texel_band.TexelBand.terms`)
    pi, pj : (K,) uint8           the powers of d1 and d2 of each term
    envelope, sure : (P,) float32 training envelope and its :func:`.validity.sure_bound`
    width, slope : float          the falloff's width and the continuation's order
    margin : float                how far the detail may exceed its envelope (:data:`.validity.MARGIN`)
    """

    corner: np.ndarray
    weight: np.ndarray
    terms: np.ndarray
    pi: np.ndarray
    pj: np.ndarray
    envelope: np.ndarray
    sure: np.ndarray
    width: float
    slope: float
    margin: float

    @classmethod
    def build(cls, texel_rho: sp.csr_matrix, terms: np.ndarray, envelope: np.ndarray, sure: np.ndarray,
              width: float, slope: float, margin: float) -> "TexelValidity":
        """From the band's ρ operator (P,Q) CSR float64 with at most 3 entries a row (a
        barycentric interpolation), its ``terms`` (K,1,P) float32, envelope and sure bound (P,),
        and the validity's falloff ``width``, continuation ``slope`` and ``margin``."""
        R = sp.csr_matrix(texel_rho)
        P = R.shape[0]
        nnz = np.diff(R.indptr)
        if R.dtype != np.float64 or nnz.max(initial=0) > CORNERS or terms.shape[1] != 1 or terms.shape[2] != P:
            raise ValueError(f"need a float64 (P,Q) operator of ≤ {CORNERS} entries a row and (K,1,P) terms, "
                             f"got {R.dtype} {R.shape} (≤ {nnz.max(initial=0)} a row) and {terms.shape}")
        corner = np.empty((CORNERS, P), np.uint32)
        weight = np.empty((CORNERS, P), np.float64)
        padded_rows(R.indptr, R.indices, R.data, corner, weight)
        powers = np.array(TERM_POWERS[_order_of(terms.shape[0])], np.uint8)
        return cls(corner, weight, np.ascontiguousarray(terms, np.float32), powers[:, 0].copy(),
                   powers[:, 1].copy(), np.ascontiguousarray(envelope, np.float32),
                   np.ascontiguousarray(sure, np.float32), float(width), float(slope), float(margin))

    def evaluate(self, d1: np.ndarray, d2: np.ndarray, point_rho: np.ndarray, s: int, e: int,
                 out: np.ndarray) -> np.ndarray:
        """D̃ of points ``s:e`` at their d1, d2 (F,e−s) float32 written into ``out`` (F,e−s)
        float32, C-contiguous rows (:func:`.validity.valid_scalar_polynomial` of the block, bit
        for bit), for ρ (F,Q) float64 at the UV points; returns the points outside (ρ > 1) per frame (F,) int64."""
        F, n = len(d1), e - s
        rho = np.empty((F, n), np.float32)
        flag = np.empty(n, np.bool_)
        count = np.zeros(F, np.int64)
        d1 = np.ascontiguousarray(d1, np.float32)
        d2 = np.ascontiguousarray(d2, np.float32)
        for f in range(F):
            count[f] = texel_gauge(s, e, point_rho[f], self.corner, self.weight, rho[f])
        continued = bool(count.any())
        for f in range(F):
            polynomial_flags(s, e, d1[f], d2[f], rho[f], self.terms, self.sure, continued, out[f], flag)
            repair(s, np.flatnonzero(flag), d1[f], d2[f], rho[f], self.terms, self.pi, self.pj, self.envelope,
                   np.float32(self.width), np.float32(self.slope), np.float32(1 + self.margin), continued, out[f])
        return count
