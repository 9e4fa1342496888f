"""The fine band as a polynomial of the surface's own strain (issue 17, failure mode 2).

ma2008 §4.1 drives every band by the two parameters d1, d2 of a texel: the 5D deformation
vector S (the marker's offset and the strains E^u, E^v of its two-ring, eq. 2) projected
on its first two principal axes (eq. 3), interpolated over the coarse marker mesh. For the
fine band (pores, the fine part of wrinkles) that is the wrong pair of numbers: S's
principal axes follow the offsets (millimetres where the strains are per cent), the strain
of a marker's two-ring is a centimetre-scale average, and shear is not in S at all. On the
sample actors the fine polynomial in (d1, d2) leaves half of its own training signal (map
part of the detail error 0.50–0.66 on every held-out row of both families, 0.50–0.65 on its
training frames; README, "Generalization report on the current defaults").

The fine band here is a polynomial in the Green strain of the synthesized surface itself
at the texel, ``s = (E_TT, E_BB, √2 E_TB)`` in the neutral's UV frame
(:class:`service.geometry.surface_strain.StressField`, interpolated from the vertices to
the texel), each component scaled by its training RMS σ_c:

    f_p(s) = Σ_k a_p,k m_k(s / σ),
    m = (1, x, y, z)                                   linear       (K = 4)
        (1, x, y, z, x², y², z², xy, xz, yz)           biquadratic  (K = 10, ma2008's degree)

fitted per texel by ridge least squares to the same high-passed residual targets as
ma2008's fine PDM (§4), ``min Σ_t (f_p(s_t) − y_t)² + λ tr(G_p)/K ‖a_p‖²`` with G_p the
texel's normal matrix. The mesh at synthesis is the mesh the model makes (the marker
regression's or the medium PDM's), and training takes the strain of that same mesh on the
training frames, so features mean the same at both ends.

Guards, so a pose outside the training does not extrapolate a polynomial:

* the strains are clamped per vertex to the box of its training strains, widened by
  ``margin`` × its extent on each side (``extrapolation_margin``; None: not clamped), before
  they are taken to the texels;
* the value is clipped to the range of the texel's training targets, widened the same way;
* with the medium band's validity ρ (:mod:`.validity`), the value fades by w(ρ) toward
  f_p(0) = a_p,0, the neutral's fine value (the static neutral map):
  ``f̃ = a_0 + w(ρ) (f − a_0)``, w = :func:`service.methods.confidence.falloff`.

Measured (``benchmarks/generalization_report.py --split --conditions clean``, level-0 sample
actors, 8 map frames a performance, PDM biquadratic with its other defaults; detail rel err,
full = mesh part / map part: the model's mesh with the truth's map / the truth's mesh with
the model's map). The fine band at 1024² learned from the actors' 512² maps (the former
default) loses as much again as the driver: a band finer than its data learns the data's
interpolation, and box-filtered back to 512² keeps about half of the pore-scale detail
(hence ``fine_resolution`` null, the clips' map resolution). At 512², the driver chosen on
family a (λ = 1e-3; 2 Laplacian smoothing steps of the strain no better, λ = 0.1 worse out of
range, linear within 0.02 of the biquadratic) and confirmed on b:

====== ============ ================= ================= =================
family input        d1, d2 at 1024²   d1, d2 at 512²    strain at 512²
====== ============ ================= ================= =================
a      in range     0.63 = 0.36/0.51  0.42 = 0.36/0.21  0.41 = 0.36/0.19
a      combinations 0.66 = 0.43/0.51  0.47 = 0.43/0.21  0.46 = 0.43/0.18
a      out of range 0.48 = 0.10/0.48  0.24 = 0.10/0.22  0.22 = 0.10/0.21
b      in range     0.59 = 0.15/0.57  0.35 = 0.15/0.33  0.24 = 0.15/0.21
b      combinations 0.85 = 0.58/0.64  0.76 = 0.58/0.51  0.67 = 0.58/0.36
b      out of range 0.55 = 0.13/0.53  0.44 = 0.13/0.42  0.26 = 0.13/0.23
====== ============ ================= ================= =================

The albedo PTM (§6) keeps d1, d2.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

#: monomials per order: powers of (x, y, z) = s / σ, the constant first
TERM_POWERS = {
    "linear": ((0, 0, 0), (1, 0, 0), (0, 1, 0), (0, 0, 1)),
    "biquadratic": ((0, 0, 0), (1, 0, 0), (0, 1, 0), (0, 0, 1), (2, 0, 0), (0, 2, 0), (0, 0, 2),
                    (1, 1, 0), (1, 0, 1), (0, 1, 1)),
}
#: λ of the per-texel ridge, relative to tr(G_p)/K (module docstring: chosen on family a)
RIDGE = 1e-3
#: the stored fields, in the constructor's order (:meth:`StrainBand.arrays`)
MEMBERS = ("coeffs", "scale", "vertex_box", "target_range")


def strain_order(order: str) -> str:
    """The strain band's order for a PDM of ``order`` (bicubic: the biquadratic's 10 terms,
    already as many as a cubic in d1, d2)."""
    return "linear" if order == "linear" else "biquadratic"


def monomials(x: np.ndarray, order: str) -> np.ndarray:
    """The terms (…,K) of features x (…,3) (:data:`TERM_POWERS`)."""
    x = np.asarray(x)
    out = np.empty(x.shape[:-1] + (len(TERM_POWERS[order]),), x.dtype)
    for k, powers in enumerate(TERM_POWERS[order]):
        term = np.ones(x.shape[:-1], x.dtype)
        for c, p in enumerate(powers):
            if p:
                term = term * x[..., c] ** p
        out[..., k] = term
    return out


@dataclass(frozen=True)
class StrainBand:
    """A strain-driven scalar band over P texels of an n-vertex mesh (module docstring).

    coeffs : (P,K) float32          a_p,k, mm (term order of :data:`TERM_POWERS`)
    scale : (3,) float64            σ, the training RMS of each strain component at the texels
    vertex_box : (n,2,3) float32    each vertex's training strains' lower and upper bounds
    target_range : (P,2) float32    the training targets' lower and upper bounds, mm
    """

    coeffs: np.ndarray
    scale: np.ndarray
    vertex_box: np.ndarray
    target_range: np.ndarray

    @property
    def order(self) -> str:
        return next(o for o, t in TERM_POWERS.items() if len(t) == self.coeffs.shape[1])

    def permuted(self, order: np.ndarray) -> "StrainBand":
        """The band with its texels in ``order`` (P,) (indices into these texels), its
        ``coeffs`` laid out term-major: the transpose of a C-ordered (K,P), which the
        compiled pass reads as it is (:meth:`compiled`)."""
        return StrainBand(np.ascontiguousarray(self.coeffs[order].T).T, self.scale, self.vertex_box,
                          np.ascontiguousarray(self.target_range[order]))

    def clamp(self, strain: np.ndarray, margin: float | None) -> tuple[np.ndarray, np.ndarray]:
        """Vertex strains (…,n,3) float32 clamped to the vertices' training box widened by
        ``margin`` × its extent (None: unchanged), and the fraction (…) of vertices clamped."""
        strain = np.asarray(strain, np.float32)
        if margin is None:
            return strain, np.zeros(strain.shape[:-2])
        lo, hi = self._widened(float(margin))
        out = np.minimum(np.maximum(strain, lo), hi)
        return out, np.count_nonzero((out != strain).any(axis=-1), axis=-1) / max(strain.shape[-2], 1)

    def _widened(self, margin: float) -> tuple[np.ndarray, np.ndarray]:
        """The vertex box (n,3) float32 lower and upper bounds widened by ``margin`` (made
        once per margin: a frame's clamp is then two passes over n × 3)."""
        cache = self.__dict__.setdefault("_widened_by", {})     # frozen: not a field
        if margin not in cache:
            lo, hi = self.vertex_box[:, 0], self.vertex_box[:, 1]
            pad = np.float32(margin) * (hi - lo)
            cache[margin] = (lo - pad, hi + pad)
        return cache[margin]

    def __call__(self, strain: np.ndarray, interp, margin: float | None,
                 weight: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Values (F,P) float32 for vertex strains (F,n,3) taken to the texels by ``interp``
        (P,n), and the fraction (F,) of vertices whose strain was clamped; ``margin`` widens
        the guards (None: no guard), ``weight`` (F,P) in [0, 1] fades toward a_0 (module
        docstring)."""
        strain, clamped = self.clamp(strain, margin)
        x = np.stack([interp @ s.astype(np.float64) for s in strain]).astype(np.float32)
        x /= self.scale.astype(np.float32)
        v = np.einsum("fpk,pk->fp", monomials(x, self.order), self.coeffs)
        if margin is not None:
            lo, hi = self.target_range[:, 0], self.target_range[:, 1]
            pad = np.float32(margin) * (hi - lo)
            np.clip(v, lo - pad, hi + pad, out=v)
        if weight is not None:
            a0 = self.coeffs[:, 0]
            v = a0 + np.asarray(weight, np.float32) * (v - a0)
        return v.astype(np.float32, copy=False), clamped

    def compiled(self, strain: np.ndarray, texels: "TexelStrain", margin: float | None,
                 fade: "TexelFade | None", out: np.ndarray) -> float:
        """One frame of :meth:`__call__` on the compiled pass (:mod:`.strain_texels`): the
        vertices' strain (n,3) clamped, taken to the texels by ``texels``, faded by ``fade``
        (None: not faded), the values into ``out`` (P,) float32; the fraction of vertices
        clamped."""
        from service.geometry import ranges
        from service.methods.pdm.strain_texels import texel_values     # Numba: loaded on first use

        strain, clamped = self.clamp(strain, margin)
        f = NO_FADE if fade is None else fade
        terms = np.ascontiguousarray(self.coeffs.T)         # no copy for a permuted band
        ranges.run(texel_values, len(self.coeffs), texels.corner, texels.weight, np.ascontiguousarray(strain.T),
                   (1.0 / self.scale).astype(np.float32), terms, self.target_range,
                   -1.0 if margin is None else float(margin), f.corner, f.weight,
                   np.ascontiguousarray(f.point_rho, np.float64), f.width, out)
        return float(clamped)

    def arrays(self, prefix: str) -> dict[str, np.ndarray]:
        """The model-file members ``PREFIX_coeffs``, ``_scale``, ``_vertex_box``, ``_target_range``."""
        return {f"{prefix}_{k}": getattr(self, k) for k in MEMBERS}

    @classmethod
    def from_arrays(cls, arrays, prefix: str) -> "StrainBand | None":
        """The band stored by :meth:`arrays` (None when ``arrays`` has none)."""
        if f"{prefix}_coeffs" not in arrays:
            return None
        return cls(*(np.asarray(arrays[f"{prefix}_{k}"]) for k in MEMBERS))


@dataclass(frozen=True)
class TexelStrain:
    """Vertices → texels for the compiled pass: each texel's (at most 3) vertices ``corner``
    (3,P) uint32 and barycentric weights ``weight`` (3,P) float32 (0 where a row has fewer)."""

    corner: np.ndarray
    weight: np.ndarray

    @classmethod
    def from_csr(cls, interp, dtype=np.float32) -> "TexelStrain":
        """From the interpolation CSR (P,n) of at most 3 entries a row (weights as ``dtype``;
        padded by :func:`.texel_validity.padded_rows`)."""
        from service.methods.pdm.texel_validity import CORNERS, padded_rows     # Numba

        interp = interp.tocsr()
        P = interp.shape[0]
        most = int(np.diff(interp.indptr).max(initial=0))
        if most > CORNERS:
            raise ValueError(f"a texel interpolates {most} vertices, at most {CORNERS} expected")
        corner, weight = np.empty((CORNERS, P), np.uint32), np.empty((CORNERS, P), dtype)
        padded_rows(interp.indptr, interp.indices, interp.data, corner, weight)
        return cls(corner, weight)

    def arrays(self, prefix: str) -> dict[str, np.ndarray]:
        """``PREFIX_corner``, ``PREFIX_weight`` (a model cache's members)."""
        return {f"{prefix}_corner": self.corner, f"{prefix}_weight": self.weight}

    @classmethod
    def from_arrays(cls, arrays, prefix: str) -> "TexelStrain | None":
        """The operator stored by :meth:`arrays` (None when ``arrays`` has none)."""
        if f"{prefix}_corner" not in arrays or f"{prefix}_weight" not in arrays:
            return None
        return cls(np.asarray(arrays[f"{prefix}_corner"]), np.asarray(arrays[f"{prefix}_weight"]))


@dataclass(frozen=True)
class TexelFade:
    """One frame's fade for the compiled pass: the UV points' gauge ``point_rho`` (Q,) float64,
    the ρ operator to the texels padded (``corner`` (3,P) uint32, ``weight`` (3,P) float64:
    :class:`.texel_validity.TexelValidity`'s) and the falloff's ``width``."""

    corner: np.ndarray
    weight: np.ndarray
    point_rho: np.ndarray
    width: float


#: the compiled pass's "no fade" (width < 0)
NO_FADE = TexelFade(np.zeros((3, 0), np.uint32), np.zeros((3, 0)), np.zeros(0), -1.0)


class StrainFit:
    """Accumulates the per-texel normal equations over chunks of training frames, in raw
    strain units (σ is known only at the end; the monomials' scaling is applied to the sums
    then), with the vertices' strain box and the targets' range."""

    def __init__(self, points: int, vertices: int, order: str):
        self.order = order
        K = len(TERM_POWERS[order])
        self.G = np.zeros((points, K, K))
        self.b = np.zeros((points, K))
        self.yy = np.zeros(points)
        self.sq = np.zeros(3)
        self.count = 0
        self.box = np.stack([np.full((vertices, 3), np.inf), np.full((vertices, 3), -np.inf)], axis=1)
        self.range = np.stack([np.full(points, np.inf), np.full(points, -np.inf)], axis=1)

    def add(self, strain: np.ndarray, interp, targets: np.ndarray) -> None:
        """Frames' vertex strains (f,n,3), taken to the texels by ``interp`` (P,n), and their
        targets (f,P) at the texels."""
        strain = np.asarray(strain, np.float32)
        np.minimum(self.box[:, 0], strain.min(axis=0), out=self.box[:, 0])
        np.maximum(self.box[:, 1], strain.max(axis=0), out=self.box[:, 1])
        np.minimum(self.range[:, 0], np.min(targets, axis=0), out=self.range[:, 0])
        np.maximum(self.range[:, 1], np.max(targets, axis=0), out=self.range[:, 1])
        K = self.G.shape[1]
        for v, y in zip(strain, np.asarray(targets, np.float64)):     # a frame at a time: (P,K) terms
            x = interp @ v.astype(np.float64)
            X = monomials(x, self.order)
            for k in range(K):                                     # the upper triangle, mirrored
                self.G[:, k, k:] += X[:, k:] * X[:, k, None]
            self.b += X * y[:, None]
            self.yy += y * y
            self.sq += np.einsum("pc,pc->c", x, x)
            self.count += len(x)

    def solve(self, ridge: float = RIDGE, anchor: np.ndarray | None = None) -> StrainBand:
        """The band of least ridge error (module docstring); with ``anchor`` (P,) the constant
        term is fixed to it (the neutral's fine value, so zero strain gives the neutral's map
        exactly) and the others fitted to ``y − anchor``."""
        scale = np.sqrt(self.sq / max(self.count, 1))
        scale = np.where(scale > 0, scale, 1.0)
        c = self._term_scale(scale)
        self._mirror()
        G = self.G * (c[:, None] * c[None, :])
        b = self.b * c
        coeffs = np.zeros(b.shape)
        free = 0 if anchor is None else 1
        if anchor is not None:          # G[:, k, 0] = Σ_t m_k (term 0 is the constant)
            coeffs[:, 0] = anchor
            b = b - anchor[:, None] * G[:, :, 0]
        G, b = G[:, free:, free:], b[:, free:]
        K = G.shape[1]
        lam = ridge * np.einsum("pkk->p", G) / K
        G[:, np.arange(K), np.arange(K)] += np.maximum(lam, 1e-30)[:, None]
        coeffs[:, free:] = np.linalg.solve(G, b[..., None])[..., 0]
        return StrainBand(coeffs.astype(np.float32), scale, self.box.astype(np.float32),
                          self.range.astype(np.float32))

    def _mirror(self) -> None:
        """G's lower triangle from its upper one (what :meth:`add` accumulates), in place."""
        i, j = np.triu_indices(self.G.shape[1], 1)
        self.G[:, j, i] = self.G[:, i, j]

    def _term_scale(self, scale: np.ndarray) -> np.ndarray:
        """c (K,): term k of the features scaled by 1/σ is term k of the raw ones times c_k."""
        return np.array([np.prod(scale ** -np.array(p, float)) for p in TERM_POWERS[self.order]])

    def residual_sq(self, band: StrainBand) -> np.ndarray:
        """Σ_t (f_p(s_t) − y_t)² (P,) over the frames added (unguarded), from the sums:
        ``Σy² − 2 aᵀb + aᵀGa`` in raw units."""
        a = band.coeffs.astype(np.float64) * self._term_scale(band.scale)
        self._mirror()
        r = self.yy - 2 * np.einsum("pk,pk->p", a, self.b) + np.einsum("pk,pkl,pl->p", a, self.G, a)
        return np.maximum(r, 0.0)
