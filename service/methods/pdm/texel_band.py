"""One polynomial displacement map over the covered texels of an H×H map (ma2008 §4.2)."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np

from service.methods.footprint import UNREAD
from service.methods.pdm import polynomial
from service.methods.pdm.deformation import ParameterField
from service.methods.pdm.extrapolation import limit_parameters
from service.methods.pdm.validity import BandValidity

#: points per block of :meth:`TexelBand.synthesize` (about 0.25 MB per float32 row: the
#: block's temporaries stay in the cache between the passes)
BLOCK_POINTS = 65536


@dataclass(frozen=True)
class CoveredTexels:
    """The covered texels of an H×H map: resolution H and their flat indices ``index`` (P,)
    (0 and the UV point indices for the medium PDM sampled at the mesh's UV points)."""

    resolution: int
    index: np.ndarray

    def mask(self) -> np.ndarray:
        """(H,W) bool: the covered texels."""
        m = np.zeros(self.resolution ** 2, bool)
        m[self.index] = True
        return m.reshape(self.resolution, self.resolution)

    def image(self, values: np.ndarray, channels: bool = False) -> np.ndarray:
        """Covered-texel values (…,P) or, with ``channels``, (…,P,C) → maps (…,H,W[,C]) float32; 0 elsewhere."""
        values = np.asarray(values)
        lead = values.shape[:-2] if channels else values.shape[:-1]
        C = values.shape[-1] if channels else 1
        H = self.resolution
        out = np.zeros(lead + (H * H, C), np.float32)
        out[..., self.index, :] = values.reshape(lead + (len(self.index), C))
        return out.reshape(lead + (H, H) + ((C,) if channels else ()))


@dataclass(frozen=True)
class CoefficientMap(CoveredTexels):
    """A stored PDM (:class:`~service.methods.pdm.data.PdmData`): the polynomial coefficients
    ``coeffs`` (P,C,K) float32 (§4.2) of the covered texels, row-major.

    Synthesis never reads ``coeffs``: it evaluates :class:`TexelBand`'s term-major copy
    (stored in the model's cache, or made from ``coeffs`` once at load). So the model
    cache does not weigh them while they are mapped (:data:`~service.methods.footprint.UNREAD`;
    a level-1 PDM's fine and albedo maps: 28.6 MB of the 379 MB it was weighed at, never
    paged in by any output; issue 23's weight against the resident cost).
    """

    coeffs: np.ndarray = dataclasses.field(metadata=UNREAD)


@dataclass(frozen=True)
class TexelBand(CoveredTexels):
    """One PDM as synthesis evaluates it (built by :meth:`build`, unchanged afterwards).

    index : (P,)               the points, in evaluation order (grouped by coarse element
                               for the fine and albedo texels)
    coeffs : (P,C,K) float32   polynomial coefficients (§4.2), a view of ``terms`` (K,C,P),
                               the same term-major (contiguous per term; one copy in memory)
    field : ParameterField     d1, d2 at the points
    limit : (4,P) float32      extrapolation limit per point (:func:`service.methods.pdm.model._limits`):
                               the inverse second moment (i11, i12, i22) of the training
                               (d1, d2) and the largest training Mahalanobis radius R (None:
                               the band is not limited)
    """

    coeffs: np.ndarray
    field: ParameterField
    limit: np.ndarray | None
    terms: np.ndarray = dataclasses.field(repr=False)

    @classmethod
    def build(cls, resolution: int, index: np.ndarray, coeffs: np.ndarray | None, field: ParameterField,
              limit: np.ndarray | None = None, terms: np.ndarray | None = None) -> "TexelBand":
        """From the coefficients (P,C,K) in the points' order, or their term-major copy
        ``terms`` (K,C,P) float32 as stored (a model's cache, C-contiguous: used as it is,
        ``coeffs`` then not read; issue 23: the fine and albedo bands' copies were ~85 ms of
        a level-1 load)."""
        if terms is None:
            terms = np.ascontiguousarray(np.asarray(coeffs).transpose(2, 1, 0))
        return cls(resolution, index, terms.transpose(2, 1, 0), field, limit, terms)

    def parameters(self, S: np.ndarray, margin: float | None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """d1, d2 (F,P) for S (F,M,5), limited to ``(1 + margin)`` × the training radius
        (None: unlimited; see :func:`service.methods.pdm.model._limits`), and the fraction (F,) of points limited."""
        d1, d2 = self.field(S)
        if margin is None:
            return d1, d2, np.zeros(len(S))
        d1, d2, over = limit_parameters(d1, d2, self.limit, margin)
        return d1, d2, np.count_nonzero(over, axis=-1) / max(over.shape[-1], 1)

    def evaluate(self, d1: np.ndarray, d2: np.ndarray) -> np.ndarray:
        """The PDM (…,P,C), C-contiguous, at parameters d1, d2 (…,P) (ma2008 eq. 1)."""
        return np.ascontiguousarray(polynomial.evaluate(self.terms.transpose(2, 1, 0), d1, d2))

    def synthesize(self, S: np.ndarray, margin: float | None,
                   validity: BandValidity | None = None) -> tuple[np.ndarray, np.ndarray]:
        """The PDM (F,P,C) float32 at the parameters of S (F,M,5), and the fraction (F,) of
        points limited: ``evaluate(*parameters(S, margin)[:2])`` bit for bit, block by block;
        with ``validity`` (:meth:`.validity.Validity.band`, ``margin`` then None), the
        values continued and faded outside the validity region
        (:func:`.validity.valid_values` of the whole band, bit for bit) and the fraction of
        points outside it.

        Points sorted by coarse element (``field.runs``) are done in blocks of about
        ``BLOCK_POINTS`` whole element runs: parameters (eq. 3), extrapolation limit or
        validity and polynomial (eq. 1) of one block are computed while its temporaries
        are in the cache, instead of each pass streaming arrays of all P points (on the
        715k texels of a 1024² fine map: 12.1 → 9.2 ms of CPU per frame, measured with other
        jobs running). The element terms are computed once for all blocks, and each block
        runs the same arithmetic per point (:meth:`.deformation.ParameterField.combine`, then
        elementwise) as the whole-band path.
        """
        T, P = len(S), len(self.index)
        if self.field.runs is None:
            d1, d2, frac = self.parameters(S, margin)
            if validity is None:
                return self.evaluate(d1, d2), frac
            return validity.evaluate(d1, d2), validity.outside() / max(P, 1)
        g = self.field.element_terms(S)
        starts = self.field.run_starts
        terms = self.terms
        out = np.empty((T, P, terms.shape[1]), np.float32)
        over = np.zeros(T, np.int64)
        for a, b in self.field.blocks(BLOCK_POINTS):
            s, e = starts[a], starts[b]
            d1, d2 = self.field.combine(g, a, b)
            if margin is not None:
                d1, d2, hit = limit_parameters(d1, d2, self.limit[:, s:e], margin)
                over += np.count_nonzero(hit, axis=-1)
            if validity is None:
                out[:, s:e] = polynomial.evaluate(terms[..., s:e].transpose(2, 1, 0), d1, d2)
            else:
                over += validity.block(d1, d2, s, e, out[:, s:e])
        frac = over / max(P, 1) if margin is not None or validity is not None else np.zeros(T)
        return out, frac
