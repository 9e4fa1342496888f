"""Region-weighted interpolation of database detail and colours (bermano2014 §5.4 eq. 4, §5.5).

For triangle t and shape-space component i (eq. 4):

    b_h[t,i] = Σ_r  ω̂_{r,t} · Σ_k w_{r,k} D_h[k,t,i],        ω̂_{r,t} = ω_{r,t} / Σ_ρ ω_{ρ,t}

— within each region the database frames are blended with that region's matched convex
weights w_r, and the regions are blended with their normalized soft weights. Per-vertex
colours use the same scheme with per-vertex region weights (§5.5, last paragraph).

Only frames with a non-zero weight in some region are read: the per-frame cost is
O(m · K) for K active frames, not O(m · |D|). The per-element sum over them is compiled
(:mod:`.blend_kernel`, bit for bit the NumPy passes it replaced).
"""

from __future__ import annotations

import numpy as np

from service.methods.shape_space.params import WEIGHT_EPS


def active_frames(weights: np.ndarray, eps: float = WEIGHT_EPS) -> np.ndarray:
    """Indices (K,) of the database frames with a weight above ``eps`` in any region."""
    return np.flatnonzero(np.any(np.asarray(weights) > eps, axis=0))


def blend(values: np.ndarray, omega_hat: np.ndarray, weights: np.ndarray,
          scale: np.ndarray | None = None, dtype=np.float64, out: np.ndarray | None = None) -> np.ndarray:
    """Region-weighted blend of per-frame, per-element values (bermano2014 eq. 4).

    Parameters
    ----------
    values : (N,k,C) float      per database frame, per element (triangle or vertex), C
                                components (9 shape-space coordinates, or colour channels)
    omega_hat : (R,k) float     normalized region weights (columns sum to 1); given in the
                                values' compute precision (float32 for float16/float32
                                values) the coefficients are formed in it
    weights : (R,N) float       matched convex weights per region (rows sum to 1)
    scale : (N,) float | None   values stored quantized, frame k's being ``scale[k] ·
                                values[k]`` (:func:`.maps.quantize`): folded into the weights
    dtype : the result's dtype (float64; float32 for a map that is kept in float32: the
            compute precision's sums as they are, without a round trip through float64)
    out : (k,C) ``dtype`` | None   written and returned (e.g. a request's work array)

    Returns
    -------
    b : (k,C) ``dtype``   summed in the values' compute precision (float32 for int16,
                          float16 and float32 values), then converted
    """
    weights = np.asarray(weights, dtype=np.float64)
    K = active_frames(weights, 0.0)
    WK = weights[:, K] if scale is None else weights[:, K] * np.asarray(scale, np.float64)[K]
    # K is small (§5.3: the weights fall off fast), so one multiply-add per active frame, in
    # the stored precision of the values (float32 halves the memory traffic)
    compute = np.result_type(np.asarray(values[:0]).dtype, np.float32)
    # (K,k): each active frame's coefficients a contiguous row (the (k,R)·(R,K) product of
    # the transposed weights took 3–9× as long), in float64 unless omega_hat is given in
    # the values' precision (a map's millions of texels: no float64 (K,k) pass)
    omega_hat = np.asarray(omega_hat)
    if omega_hat.dtype != compute:
        omega_hat = omega_hat.astype(np.float64)
    coef = (WK.T.astype(omega_hat.dtype) @ omega_hat).astype(compute, copy=False)
    if isinstance(values, np.ndarray) and values.dtype in _COMPILED and values.ndim == 3:
        from service.geometry import ranges
        from service.methods.shape_space.blend_kernel import blend_rows     # Numba: loaded on first use

        direct = out is not None and out.dtype == compute and out.flags.c_contiguous
        b = out if direct else np.empty(values.shape[1:], compute)
        args = (K.astype(np.int64), np.ascontiguousarray(coef))
        if b.shape[1] == 1:         # one component: the kernel's vectorizing (N,k) form
            ranges.run(blend_rows, b.shape[0], values[:, :, 0], *args, b[:, 0])
        else:
            ranges.run(blend_rows, b.shape[0], values, *args, b)
    else:
        b = np.zeros(np.shape(values)[1:], compute)       # e.g. float16 values: NumPy passes
        tmp = np.empty_like(b)
        for j, k in enumerate(K):
            np.multiply(values[k], coef[j, :, None], out=tmp)
            b += tmp
        direct = False
    if out is None:
        return b.astype(dtype, copy=False)
    if not direct:
        out[...] = b
    return out


#: stored dtypes the compiled sum takes (:mod:`.blend_kernel`; float16 values, older
#: models' maps, keep the NumPy passes)
_COMPILED = (np.dtype(np.int16), np.dtype(np.float32), np.dtype(np.float64))
