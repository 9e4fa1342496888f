"""Per-texel polynomial fitting and evaluation of deformation-driven PDMs (ma2008 §4, §4.2).

At every texel p a polynomial displacement map stores, per channel, the coefficients of a
polynomial in two low-frequency deformation parameters ``d1, d2`` (ma2008 eq. 1)

    D_p(d1, d2) = a0 d1² + a1 d2² + a2 d1 d2 + a3 d1 + a4 d2 + a5          (biquadratic)

fitted to the measured displacements ``f_t`` of T training frames by the regularized
least-squares problem of ma2008 §4.2

    [ Φ       ] a = [ f ]      Φ_tk = d1_t^i_k d2_t^j_k,
    [ diag(w) ]     [ 0 ]      w_k = γ / (σ1^i_k σ2^j_k),  w_const = 0,

with σ1, σ2 the standard deviations of d1, d2 over the training frames at that texel. The
γ rows keep a coefficient whose parameter barely varied from blowing up.

Two ridges (``fit``'s ``gamma`` and ``ridge``): ``gamma`` gives the paper's rows above;
without it the default is the dimensionless ridge (issue 17, "the fine map is 4× too weak"
on family b)

    w_k = ρ ‖Φ_k‖ = ρ (Σ_t Φ_tk²)^½,  w_const = 0      (ρ = ``ridge``).

The paper's rows are not dimensionless: against the data energy ``Σ_t Φ_tk² ≈ T σ^{2(i+j)}``
they weigh ``γ² / (T σ^{4(i+j)})``, so one γ is a different ridge for every unit of d1, d2,
number of frames, actor and texel (d1, d2 are in mm here). Measured on the fine band (512²,
γ = 30, median over the face texels of ridge / data energy): family a (T = 160, median σ1,
σ2 = 2.2, 1.1 mm) 0.24 on d1, 3.3 on d2, 0.36 on d2²; family b (T = 260, σ = 1.4, 0.55 mm)
0.93, 35 and 58, i.e. b's d2 terms were shrunk 35–60× and its fine fit kept only a third of
the dynamic signal it could fit (dynamic R² 0.34 against 0.59 unregularized). The ``ridge``
rows scale each term's row by its own RMS over the texel's frames, so ``ρ²`` *is* the ridge
/ data energy of every term at every texel — the ridge of the column-normalized (Jacobi-
scaled) system, ``Â + ρ² I`` on the non-constant terms — the same for any unit, frame count
and actor. It still does what the paper asks of the γ rows: a parameter that never varied
contributes a column (nearly) parallel to the constant's, which the unregularized constant
absorbs while its own coefficient is pulled to 0; a parameter that is 0 in every frame gives
a zero column, solved in the minimum-norm sense (coefficient 0).

Solved through the normal equations ``(ΦᵀΦ + diag(w²)) a = Φᵀf``, all texels and channels
at once: ΦᵀΦ is assembled from the distinct monomial moments ``Σ_t d1^a d2^b`` (15 for
the biquadratic, not K² = 36 products), accumulated by a Python loop over blocks of frames
that is vectorized over a chunk of texels (never a loop over texels); the K×K systems are
then Jacobi-scaled and solved by batched ``np.linalg.solve``.

Neutral anchor (``fit``'s ``anchor``; issue 17, failure mode 1). The paper leaves the
constant a5 free, so it is the intercept of the fit over all frames: wherever the data are
not exactly polynomial (a wrinkle that only appears beyond some compression), the fitted
surface misses the texel's value at d = 0 and every expression that keeps the texel near
rest gets that offset — while the safe fallback (the thin shell, the static neutral map) is
exactly the neutral. Given the value f0 (P,C) the texel must take at zero deformation (the
neutral's detail, known), the constant is fixed to it, ``a5 = f0``, and the other terms are
fitted to ``f − f0`` with the same ridge: the equality-constrained least squares whose
solution has ``D(0, 0) = f0`` exactly. The anchor keeps D continuous with the fallback at the
neutral, so at small deformations of untrained combinations the polynomial starts from the
neutral's detail instead of an intercept.

Orders (ma2008 §4.3): ``linear`` (K = 3), ``biquadratic`` (K = 6, the paper's choice),
``bicubic`` (K = 10). Coefficients are stored highest total degree first, the constant
term always last, as in eq. 1.
"""

from __future__ import annotations

import numpy as np

#: number of polynomial terms (coefficients per channel) of each order
ORDERS: dict[str, int] = {"linear": 3, "biquadratic": 6, "bicubic": 10}

#: (power of d1, power of d2) of each term, in coefficient order a0, a1, ...; the
#: biquadratic is exactly ma2008 eq. 1; the constant term is always last
TERM_POWERS: dict[str, tuple[tuple[int, int], ...]] = {
    "linear": ((1, 0), (0, 1), (0, 0)),
    "biquadratic": ((2, 0), (0, 2), (1, 1), (1, 0), (0, 1), (0, 0)),
    "bicubic": (
        (3, 0), (0, 3), (2, 1), (1, 2), (2, 0), (0, 2), (1, 1), (1, 0), (0, 1), (0, 0),
    ),
}

#: default floor on σ1, σ2 (units of d1, d2): a parameter that never varied is treated as
#: varying by this much, which makes its γ-row weight huge and drives its terms to 0
SIGMA_FLOOR = 1e-6
#: relative eigenvalue cut-off below which an unregularized normal matrix is treated as
#: singular and solved in the minimum-norm (lstsq) sense
SINGULAR_RCOND = 1e-12
#: frames accumulated per vectorized step of ``fit`` (bounds its (block, chunk) work arrays)
FRAME_BLOCK = 8
#: texels whose K×K normal equations are solved per batched call in ``fit``
SOLVE_BLOCK = 16384


def _order(order: str) -> tuple[tuple[int, int], ...]:
    try:
        return TERM_POWERS[order]
    except KeyError:
        raise ValueError(f"unknown PDM order {order!r}; expected one of {sorted(ORDERS)}") from None


def _order_of(K: int) -> str:
    for name, k in ORDERS.items():
        if k == K:
            return name
    raise ValueError(f"{K} coefficients per channel match no PDM order {ORDERS}")


def design_matrix(d1: np.ndarray, d2: np.ndarray, order: str = "biquadratic") -> np.ndarray:
    """Polynomial terms of (d1, d2), one row of the Φ of ma2008 §4.2 per sample (eq. 1).

    Parameters
    ----------
    d1, d2 : (...) float   deformation parameters (ma2008 eq. 3), same (broadcastable) shape
    order : str            a key of ``ORDERS``

    Returns
    -------
    Phi : (..., K) float64   ``Phi[..., k] = d1^i d2^j``, ``(i, j) = TERM_POWERS[order][k]``;
                             for the biquadratic ``[d1², d2², d1 d2, d1, d2, 1]``
    """
    powers = _order(order)
    d1, d2 = np.broadcast_arrays(np.asarray(d1, np.float64), np.asarray(d2, np.float64))
    return np.stack([d1**i * d2**j for i, j in powers], axis=-1)


def regularization_weights(
    order: str,
    sigma1: float | np.ndarray,
    sigma2: float | np.ndarray,
    gamma: float,
    sigma_floor: float = SIGMA_FLOOR,
) -> np.ndarray:
    """Diagonal of the γ rows of ma2008 §4.2: ``w_k = γ / (σ1^i_k σ2^j_k)``, 0 for the constant.

    Parameters
    ----------
    order : str                   a key of ``ORDERS``
    sigma1, sigma2 : float or (P,) standard deviations of d1, d2 over the training frames
    gamma : float                 regularization constant γ ≥ 0 (dimensionless: w_k a_k has
                                  the units of the displacement)
    sigma_floor : float           σ below this (units of d1, d2), or NaN, is replaced by it

    Returns
    -------
    w : (K,) or (P,K) float64

    Notes
    -----
    A parameter that never varied (σ → 0) would give an infinite weight; the floor keeps the
    weight finite but large (γ / floor^i), so that the terms of that parameter are driven to
    ≈ 0 and the constant absorbs their mean contribution. The constant term is not
    regularized.
    """
    if gamma < 0:
        raise ValueError(f"gamma must be >= 0, got {gamma}")
    powers = np.array(_order(order))
    s1 = np.fmax(np.asarray(sigma1, np.float64), sigma_floor)[..., None]   # NaN → floor
    s2 = np.fmax(np.asarray(sigma2, np.float64), sigma_floor)[..., None]
    w = gamma / (s1 ** powers[:, 0] * s2 ** powers[:, 1])
    return np.where((powers[:, 0] + powers[:, 1]) == 0, 0.0, w)


def relative_ridge_weights(order: str, column_norms: np.ndarray, ridge: float) -> np.ndarray:
    """Diagonal of the dimensionless ridge rows (module docstring): ``w_k = ρ ‖Φ_k‖``, 0 for
    the constant.

    Parameters
    ----------
    order : str                 a key of ``ORDERS``
    column_norms : (..., K)     ``‖Φ_k‖ = (Σ_t Φ_tk²)^½`` over a texel's training frames (units
                                of d1^i d2^j; the square roots of the normal matrix's diagonal)
    ridge : float               ρ ≥ 0, dimensionless: ``ρ²`` is the ridge / data energy of every
                                non-constant term

    Returns
    -------
    w : (..., K) float64
    """
    if ridge < 0:
        raise ValueError(f"ridge must be >= 0, got {ridge}")
    powers = np.array(_order(order))
    norms = np.asarray(column_norms, np.float64)
    if norms.shape[-1:] != (len(powers),):
        raise ValueError(f"expected column norms (..., {len(powers)}) for order {order!r}, got {norms.shape}")
    return np.where((powers[:, 0] + powers[:, 1]) == 0, 0.0, ridge * norms)


def _moment_index(powers: tuple[tuple[int, int], ...]) -> tuple[np.ndarray, np.ndarray]:
    """Distinct monomials (n_mon,2) of the products of two terms, and (K,K) index into them."""
    p = np.array(powers)
    pair = (p[:, None, :] + p[None, :, :]).reshape(-1, 2)
    monomials, inverse = np.unique(pair, axis=0, return_inverse=True)
    return monomials, inverse.reshape(len(p), len(p))


def _solve_normal(
    A: np.ndarray, b: np.ndarray, check: np.ndarray, pinv: bool = False
) -> np.ndarray:
    """Solve SPD-or-singular systems ``A x = b``, (...,K,K) and (...,K,R), Jacobi-scaled.

    Systems flagged in ``check`` (...) may be singular: those whose scaled eigenvalues fall
    below ``SINGULAR_RCOND`` × the largest (all flagged ones if ``pinv``) get the
    minimum-norm least-squares solution (pseudo-inverse) of the scaled system instead.
    Should LU still fail, the batch is redone with every system checked, then pseudo-inverted.
    """
    diag = np.diagonal(A, axis1=-2, axis2=-1)
    s = np.where(diag > 0, 1.0 / np.sqrt(np.where(diag > 0, diag, 1.0)), 1.0)
    As = A * s[..., :, None] * s[..., None, :]
    bs = b * s[..., :, None]
    x = np.zeros_like(bs)
    singular = np.zeros(check.shape, dtype=bool)
    if check.any():
        lam = np.linalg.eigvalsh(As[check])
        bad = lam[:, 0] <= SINGULAR_RCOND * np.maximum(lam[:, -1], np.finfo(np.float64).tiny)
        bad |= pinv
        if bad.any():
            idx = tuple(i[bad] for i in np.nonzero(check))
            singular[idx] = True
            lam, V = np.linalg.eigh(As[idx])
            keep = lam > SINGULAR_RCOND * lam[:, -1:]
            inv = np.where(keep, 1.0 / np.where(keep, lam, 1.0), 0.0)
            x[idx] = np.einsum("nkl,nl,nml,nmr->nkr", V, inv, V, bs[idx], optimize=True)
    good = ~singular
    try:
        if good.all():
            x = np.linalg.solve(As, bs)
        elif good.any():
            x[good] = np.linalg.solve(As[good], bs[good])
    except np.linalg.LinAlgError:
        return _solve_normal(A, b, np.ones_like(check), pinv=bool(check.all()))
    return x * s[..., :, None]


def _fit_chunk(d1, d2, f, order, ridge, gamma, sigma, sigma_floor, anchor=None):
    """Coefficients (n,C,K) for a chunk: d1, d2 (T,n), f (T,n,C), sigma (n,2) or None;
    ``gamma`` None: the relative ridge ``ridge``, else the paper's γ rows; ``anchor`` (n,C)
    or None: the constant fixed to it, the other terms fitted to ``f − anchor``."""
    powers = TERM_POWERS[order]
    if anchor is not None:
        f = f - anchor[None].astype(f.dtype)
    T, n, C = f.shape
    K = len(powers)
    monomials, index = _moment_index(powers)
    const = powers.index((0, 0))
    deg = int(monomials.max()) + 1

    valid = np.isfinite(f) & (np.isfinite(d1) & np.isfinite(d2))[..., None]   # (T,n,C)
    all_valid = bool(valid.all())
    shared = all_valid or bool((valid == valid[..., :1]).all())   # same rows for all channels
    mask = valid[..., :1] if shared else valid                    # (T,n,Cm)
    rows = valid.any(axis=2)                                      # texel measured at frame t
    ref1 = np.zeros(n)                                            # d at the first measured
    ref2 = np.zeros(n)                                            # frame: shift for σ
    paper = gamma is not None
    if paper and sigma is None:
        for t in range(T - 1, -1, -1):
            ref1 = np.where(rows[t], d1[t], ref1)
            ref2 = np.where(rows[t], d2[t], ref2)

    # Σ_t over blocks of frames (a Python loop over frames, vectorized over texels)
    M = np.zeros((len(monomials), n, mask.shape[2]))             # Σ_t m d1^a d2^b
    B = np.zeros((K, n, C))                                       # Σ_t m φ_k f
    S = np.zeros((2, 2, n))                                       # Σ_t (d - ref), Σ_t (d - ref)²
    nb = min(T, FRAME_BLOCK)
    X = np.empty((deg, nb, n))                                    # d1^a, a < deg
    Y = np.empty((deg, nb, n))                                    # d2^b
    Xm = X if all_valid else np.empty_like(X)                     # m d1^a
    Xf = np.empty((max(i for i, _ in powers) + 1, nb, n))         # f d1^i
    for t0 in range(0, T, nb):
        t1 = min(t0 + nb, T)
        b = t1 - t0
        X[0, :b] = Y[0, :b] = 1.0
        x, y, ft = d1[t0:t1], d2[t0:t1], f[t0:t1]
        if not all_valid:
            x = np.where(rows[t0:t1], x, 0)
            y = np.where(rows[t0:t1], y, 0)
            ft = np.where(valid[t0:t1], ft, 0)
        for a in range(1, deg):
            np.multiply(X[a - 1, :b], x, out=X[a, :b])
            np.multiply(Y[a - 1, :b], y, out=Y[a, :b])
        for cm in range(mask.shape[2]):
            if not all_valid:
                np.multiply(X[:, :b], mask[t0:t1, :, cm], out=Xm[:, :b])
            for m, (i, j) in enumerate(monomials):
                M[m, :, cm] += np.einsum("tn,tn->n", Xm[i, :b], Y[j, :b])
        for c in range(C):
            np.multiply(X[: len(Xf), :b], ft[:, :, c], out=Xf[:, :b])
            for k, (i, j) in enumerate(powers):
                B[k, :, c] += np.einsum("tn,tn->n", Xf[i, :b], Y[j, :b])
        if paper and sigma is None:
            for v, (z, ref) in enumerate(((X[1, :b], ref1), (Y[1, :b], ref2))):
                dz = z - ref
                if not all_valid:
                    dz *= rows[t0:t1]
                S[v, 0] += np.einsum("tn->n", dz)
                S[v, 1] += np.einsum("tn,tn->n", dz, dz)

    count = np.full((n, 1), T) if all_valid else mask.sum(axis=0)  # (n,Cm) valid rows
    if not paper:                                                 # ρ ‖Φ_k‖
        norms = np.sqrt(np.moveaxis(M[np.diagonal(index)], 0, -1))  # (n,Cm,K)
        w = relative_ridge_weights(order, norms, ridge)           # (n,Cm,K)
    else:                                                         # γ / (σ1^i σ2^j)
        if sigma is None:
            nr = np.maximum(T if all_valid else rows.sum(axis=0), 1)  # frames measured
            sigma = np.sqrt(np.maximum(S[:, 1] / nr - (S[:, 0] / nr) ** 2, 0.0)).T   # (n,2)
        w = regularization_weights(order, sigma[:, 0], sigma[:, 1], gamma, sigma_floor)[:, None, :]

    unregularized = (np.delete(w, const, axis=-1) == 0).any(axis=-1)   # (n,1) or (n,Cm)
    check = (count < K) | unregularized                           # (n,Cm) may be singular
    coeffs = np.empty((n, C, K))
    for s in range(0, n, SOLVE_BLOCK):                            # bounds the K×K work arrays
        e = min(s + SOLVE_BLOCK, n)
        A = np.moveaxis(M[:, s:e][index], (0, 1), (-2, -1))       # (e-s,Cm,K,K)
        A[..., np.arange(K), np.arange(K)] += w[s:e] ** 2
        Bs = B[:, s:e]
        if anchor is not None:                                    # a_const = 0 on f − anchor
            A[..., const, :] = 0.0
            A[..., :, const] = 0.0
            A[..., const, const] = 1.0
            Bs = Bs.copy()
            Bs[const] = 0.0
        if shared:                                                # channels = right-hand sides
            x = _solve_normal(A[:, 0], np.moveaxis(Bs, 0, 1), check[s:e, 0])
            coeffs[s:e] = np.moveaxis(x, -1, 1)
        else:
            x = _solve_normal(A, np.moveaxis(Bs, 0, -1)[..., None], check[s:e])
            coeffs[s:e] = x[..., 0]
    if anchor is not None:
        coeffs[..., const] = anchor
    return coeffs


def fit(
    d1: np.ndarray,
    d2: np.ndarray,
    f: np.ndarray,
    order: str = "biquadratic",
    *,
    ridge: float = 0.1,
    gamma: float | None = None,
    sigma: np.ndarray | None = None,
    chunk: int = 65536,
    sigma_floor: float = SIGMA_FLOOR,
    anchor: np.ndarray | None = None,
) -> np.ndarray:
    """Regularized least-squares PDM coefficients at every texel (ma2008 §4.2, eq. 1).

    Solves per texel and channel ``[Φ; diag(w)] a = [f; 0]`` with ``Φ = design_matrix(d1, d2)``
    over the training frames and ``w = relative_ridge_weights(order, ‖Φ_k‖, ridge)`` or, when
    ``gamma`` is given, the paper's ``w = regularization_weights(order, σ1, σ2, gamma)``.

    Parameters
    ----------
    d1, d2 : (T,P) float     deformation parameters per frame and texel (ma2008 eq. 3)
    f : (T,P,C) or (T,P)     measured displacement per frame, texel and channel (mm for the
                             3D medium and 1D fine bands, reflectance for albedo); (T,P)
                             means C = 1
    order : str              ``"linear"``, ``"biquadratic"`` (eq. 1) or ``"bicubic"``
    ridge : float            ρ ≥ 0, dimensionless (ρ² = ridge / data energy of each
                             non-constant term; 0: plain least squares); ignored when
                             ``gamma`` is given
    gamma : float or None    the paper's regularization constant γ ≥ 0 (ma2008 §4.2, rows
                             γ / (σ1^i σ2^j)); None: use ``ridge``
    sigma : (P,2) or None    σ1, σ2 per texel in units of d1, d2 (anything broadcastable to
                             (P,2)), ``gamma`` mode only; None: the standard deviation of d1,
                             d2 over the frames in which the texel was measured
    chunk : int              texels solved per batch, to bound memory (see Notes)
    sigma_floor : float      σ below this is treated as this (see ``regularization_weights``)
    anchor : (P,C), (P,) or None   the value at zero deformation (module docstring, "neutral
                             anchor"): the constant term fixed to it, so
                             ``evaluate(coeffs, 0, 0) == anchor``; None: the constant is fitted
                             (the paper; bit-identical to the fit without this argument)

    Returns
    -------
    coeffs : (P,C,K) float64  ``coeffs[p,c,k]`` multiplies term k of ``TERM_POWERS[order]``

    Notes
    -----
    - Inputs may be float32; all arithmetic is float64.
    - Missing data: a NaN in ``f[t,p,c]`` (texel not seen in frame t) or in ``d1[t,p]``,
      ``d2[t,p]`` drops that row from the fit of that texel (and channel): weight 0.
    - Singular systems: with γ > 0 the normal matrix is positive definite whenever the texel
      has at least one valid row; with ρ > 0, whenever no term's column is all zero. Texels
      with fewer than K valid rows or with an unregularized term (γ or ρ = 0, a zero column)
      are checked; if their Jacobi-scaled normal matrix is
      numerically singular (eigenvalues below ``SINGULAR_RCOND`` × the largest) they get the
      minimum-norm least-squares solution (pseudo-inverse, like ``np.linalg.lstsq``, in
      Jacobi-scaled coefficients), computed for those texels only; nothing raises. A texel
      with no valid row gets all-zero coefficients.
    - Memory: Φ is never formed as a (T,chunk,K) array; frames are accumulated
      ``FRAME_BLOCK`` at a time into the moments, then the (chunk,K,K) normal matrices are
      solved ``SOLVE_BLOCK`` texels at a time.
    """
    powers = _order(order)
    d1 = np.asarray(d1)
    d2 = np.asarray(d2)
    f = np.asarray(f)
    if f.ndim == 2:
        f = f[..., None]
    if d1.ndim != 2 or d1.shape != d2.shape or f.ndim != 3 or f.shape[:2] != d1.shape:
        raise ValueError(
            f"expected d1, d2 (T,P) and f (T,P,C) or (T,P); got {d1.shape}, {d2.shape}, {f.shape}"
        )
    if chunk < 1:
        raise ValueError(f"chunk must be >= 1, got {chunk}")
    if ridge < 0:
        raise ValueError(f"ridge must be >= 0, got {ridge}")
    T, P, C = f.shape
    if gamma is not None and sigma is not None:
        sigma = np.broadcast_to(np.asarray(sigma, np.float64), (P, 2))
    if anchor is not None:
        anchor = np.asarray(anchor, np.float64)
        anchor = anchor[:, None] if anchor.ndim == 1 else anchor
        if anchor.shape != (P, C) or not np.isfinite(anchor).all():
            raise ValueError(f"anchor must be finite (P,C) = ({P},{C}) or (P,), got {anchor.shape}")
    coeffs = np.empty((P, C, len(powers)))
    for s in range(0, P, chunk):
        e = min(s + chunk, P)
        coeffs[s:e] = _fit_chunk(
            d1[:, s:e], d2[:, s:e], f[:, s:e], order, ridge, gamma,
            None if gamma is None or sigma is None else sigma[s:e], sigma_floor,
            None if anchor is None else anchor[s:e],
        )
    return coeffs


def evaluate(coeffs: np.ndarray, d1: np.ndarray, d2: np.ndarray, rho: np.ndarray | None = None,
             slope: float = 1.0) -> np.ndarray:
    """Evaluate the PDM ``D_p(d1, d2) = Σ_k a_k(p) d1^i_k d2^j_k`` (ma2008 eq. 1).

    With ``rho``, the ray continuation of :mod:`service.methods.pdm.validity` in the same
    pass: at points of ρ > 1 the polynomial is evaluated at the boundary point d/ρ with
    each term of degree k scaled by ``1 + slope · k · (ρ − 1)`` (its first-order Taylor
    expansion along the ray), ``L(d) = Σ_k a_k m_k(d/ρ) + slope (ρ − 1) Σ_k k a_k m_k(d/ρ)``;
    points of ρ ≤ 1 get D(d) bit for bit (the parameters are divided by max(ρ, 1) = 1 and
    the degree sum is added with weight 0), so one evaluation serves the whole band.

    Parameters
    ----------
    coeffs : (P,C,K) float     from ``fit``; K selects the order
    d1, d2 : (P,) or (F,P)     deformation parameters per texel, for one or F frames
    rho : like d1, optional    validity gauge ρ per point (None: the plain polynomial)
    slope : float              the continuation's order (1: linear; 0: the boundary's value)

    Returns
    -------
    D : (P,C) or (F,P,C)       displacement, in the units of the fitted f; float64 unless
                               every input is float32 (then float32, e.g. for synthesis).
                               A view of a (…,C,P) array; pass coefficients whose memory is
                               term-major (K,C,P), ``coeffs = terms.transpose(2, 1, 0)``, for
                               contiguous passes over the texels
    """
    coeffs = np.asarray(coeffs)
    powers = TERM_POWERS[_order_of(coeffs.shape[-1])]
    dtype = np.result_type(coeffs, d1, d2, np.float32)
    d1, d2 = np.broadcast_arrays(np.asarray(d1, dtype), np.asarray(d2, dtype))
    if d1.shape[-1:] != coeffs.shape[:1] or d1.ndim > 2:
        raise ValueError(
            f"expected d1, d2 (P,) or (F,P) with P = {coeffs.shape[0]}, got {d1.shape}"
        )
    grow = None
    if rho is not None:
        rho = np.broadcast_to(np.asarray(rho, dtype), d1.shape)
        if np.any(rho > 1):
            r = np.maximum(rho, dtype.type(1))
            d1, d2 = d1 / r, d2 / r                              # exact where ρ ≤ 1
            r -= 1
            r *= dtype.type(slope)
            grow = r                                             # slope (ρ − 1), 0 inside
    deg = max(max(p) for p in powers) + 1
    X, Y = [None, d1], [None, d2]
    for _ in range(2, deg):
        X.append(X[-1] * d1)
        Y.append(Y[-1] * d2)
    a = coeffs.astype(dtype, copy=False).transpose(2, 1, 0)       # (K,C,P) view
    # accumulate as (…,C,P): the innermost loop runs over texels, not over C (often 1)
    out = np.broadcast_to(a[-1], d1.shape[:-1] + a.shape[1:]).copy()   # constant term last
    tmp = np.empty_like(out)
    degree_sum = None if grow is None else np.zeros_like(out)    # Σ_k k a_k m_k
    for k, (i, j) in enumerate(powers[:-1]):                      # one pass per term
        term = X[i] if j == 0 else Y[j] if i == 0 else X[i] * Y[j]
        np.multiply(term[..., None, :], a[k], out=tmp)
        out += tmp
        if degree_sum is not None:
            if i + j != 1:
                tmp *= dtype.type(i + j)
            degree_sum += tmp
    if degree_sum is not None:
        degree_sum *= grow[..., None, :]
        out += degree_sum
    return np.swapaxes(out, -1, -2)


def fit_residual_rms(
    coeffs: np.ndarray, d1: np.ndarray, d2: np.ndarray, f: np.ndarray
) -> np.ndarray:
    """RMS over frames of the fitting residual ``evaluate(coeffs, d1_t, d2_t) − f_t``.

    Parameters
    ----------
    coeffs : (P,C,K) float
    d1, d2 : (T,P) float
    f : (T,P,C) or (T,P) float   NaN entries (no measurement) are left out

    Returns
    -------
    rms : (P,C) float64   in the units of f; NaN where a texel/channel has no valid frame
    """
    f = np.asarray(f)
    if f.ndim == 2:
        f = f[..., None]
    ss = np.zeros(f.shape[1:])
    n = np.zeros(f.shape[1:])
    for t0 in range(0, f.shape[0], FRAME_BLOCK):                 # blocks of frames
        t1 = t0 + FRAME_BLOCK
        r = evaluate(coeffs, d1[t0:t1], d2[t0:t1]) - f[t0:t1]
        ok = np.isfinite(r)
        r[~ok] = 0.0
        ss += np.einsum("tpc,tpc->pc", r, r)
        n += ok.sum(axis=0)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.sqrt(ss / n)


def loo_residuals(
    d1: np.ndarray,
    d2: np.ndarray,
    f: np.ndarray,
    order: str = "biquadratic",
    *,
    ridge: float = 0.1,
    gamma: float | None = None,
    anchor: np.ndarray | None = None,
    chunk: int = 2048,
) -> np.ndarray:
    """Leave-one-frame-out residuals of :func:`fit` at every point (the PRESS residuals).

    For the regularized least squares of ma2008 §4.2 at one point, ``a = A⁻¹ Φᵀ f`` with
    ``A = ΦᵀΦ + diag(w²)`` and hat matrix ``H = Φ A⁻¹ Φᵀ``, the residual of frame t when the
    point's polynomial is fitted without it is (Allen's PRESS identity, exact for a fixed
    ridge)

        e₍₋ₜ₎ = (f_t − φ_tᵀ a) / (1 − h_tt),      h_tt = φ_tᵀ A⁻¹ φ_t,

    so T refits cost one solve. The ridge weights w are those of :func:`fit` (``ridge``: ρ‖Φ_k‖
    over all the point's frames; ``gamma``: the paper's γ/(σ1^i σ2^j)), held fixed when a frame
    is left out. With ``anchor`` the constant is fixed (not fitted): its column leaves Φ and
    the residual is that of ``f − anchor``. A frame whose leverage is 1 (the fit goes through
    it whatever its value: fewer frames than terms) gets the residual of the constant-only
    prediction ``f_t − anchor`` (0 without anchor): nothing is known about it from the others.

    Parameters
    ----------
    d1, d2 : (T,P) float     deformation parameters (ma2008 eq. 3)
    f : (T,P,C) or (T,P)     targets, as for :func:`fit` (NaN: frame not measured; the
                             residual there is NaN and the frame does not enter the fit)
    order, ridge, gamma, anchor   as for :func:`fit`
    chunk : int              points per batch ((T,chunk,K) work arrays)

    Returns
    -------
    e : (T,P,C) float64      leave-one-out residuals, in the units of f (the PRESS statistic
                             of a point and channel is ``Σ_t e²``)
    """
    powers = _order(order)
    K = len(powers)
    const = powers.index((0, 0))
    f = np.asarray(f, np.float64)
    if f.ndim == 2:
        f = f[..., None]
    d1, d2 = np.asarray(d1, np.float64), np.asarray(d2, np.float64)
    T, P, C = f.shape
    if d1.shape != (T, P) or d2.shape != (T, P):
        raise ValueError(f"expected d1, d2 (T,P) = ({T},{P}), got {d1.shape}, {d2.shape}")
    if anchor is not None:
        anchor = np.asarray(anchor, np.float64)
        anchor = anchor[:, None] if anchor.ndim == 1 else anchor
        if anchor.shape != (P, C):
            raise ValueError(f"anchor must be (P,C) = ({P},{C}) or (P,), got {anchor.shape}")
    out = np.empty((T, P, C))
    for s in range(0, P, chunk):
        e = min(s + chunk, P)
        x, y, ft = d1[:, s:e], d2[:, s:e], f[:, s:e]
        rows = np.isfinite(x) & np.isfinite(y) & np.isfinite(ft).all(axis=-1)        # (T,n)
        Phi = design_matrix(np.where(rows, x, 0), np.where(rows, y, 0), order) * rows[..., None]   # (T,n,K)
        g = np.where(rows[..., None], ft, 0)
        if anchor is not None:
            g = (g - anchor[None, s:e]) * rows[..., None]
            Phi[..., const] = 0.0
        A = np.einsum("tnk,tnl->nkl", Phi, Phi)
        if gamma is None:
            w = relative_ridge_weights(order, np.sqrt(np.diagonal(A, axis1=1, axis2=2)), ridge)
        else:
            nr = np.maximum(rows.sum(axis=0), 1)
            mean = lambda z: np.sum(np.where(rows, z, 0), axis=0) / nr                 # noqa: E731
            sig = [np.sqrt(np.maximum(mean(z * z) - mean(z) ** 2, 0.0)) for z in (np.where(rows, x, 0), np.where(rows, y, 0))]
            w = regularization_weights(order, sig[0], sig[1], gamma)
        A[:, np.arange(K), np.arange(K)] += w**2
        if anchor is not None:
            A[:, const, :] = 0.0
            A[:, :, const] = 0.0
            A[:, const, const] = 1.0
        unregularized = (np.delete(w, const, axis=-1) == 0).any(axis=-1)
        X = _solve_normal(A, Phi.transpose(1, 2, 0), (rows.sum(axis=0) < K) | unregularized)   # A⁻¹Φᵀ (n,K,T)
        a = np.einsum("nkt,tnc->nkc", X, g)
        h = np.einsum("tnk,nkt->tn", Phi, X)
        r = g - np.einsum("tnk,nkc->tnc", Phi, a)
        free = 1.0 - h
        ok = free > 1e-9
        out[:, s:e] = np.where(ok[..., None], r / np.where(ok, free, 1.0)[..., None], g)
        out[:, s:e][~rows] = np.nan
    return out


