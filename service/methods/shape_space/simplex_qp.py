"""Convex matching: the simplex-constrained least squares of bermano2014 §5.3 (eq. 2–3).

Per region r the input's compressed shape vector ã is projected onto the convex hull of
the database's compressed vectors (the columns of D̃) in the ω_r-weighted norm:

    min_w ‖D̃ w − ã‖²_{Ω_r}   s.t.  w ≥ 0,  Σ w = 1,          Ω_r = diag(ω_r)        (3)

With the precomputed Gram matrix ``G_r = D̃ᵀ Ω_r D̃`` and ``b_r = D̃ᵀ Ω_r ã`` this is the
quadratic program ``min wᵀ G w − 2 bᵀ w`` on the probability simplex (the constant
``ãᵀ Ω_r ã`` dropped), solved *exactly* by a primal active-set method
(:func:`solve_simplex_qp`, Nocedal & Wright 2006, Algorithm 16.3, specialised to the
simplex): the free set P holds the frames with positive weight; on P the
equality-constrained problem is one small KKT solve; a negative weight shortens the step
and drops its frame; at a KKT point a frame with a negative multiplier enters. Each step
decreases the objective, so it terminates in finitely many steps, with the weights at
rounding-error distance from the optimum — unlike a projected-gradient iteration, whose
accuracy depends on a tolerance. The paper reports that "the weights quickly fall off to
nearly zero outside the immediate neighborhood of ã": the free set stays small, so each
KKT solve is tiny.

Departure: a ridge ``ε · mean(diag G) · I`` (ε = :data:`~.params.QP_RIDGE`) makes G
positive definite. Database frames are often nearly affinely dependent, and without it
the minimizer need not be unique (and the KKT matrices could be singular).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from service.methods.shape_space.params import QP_RIDGE, QP_TOL


@dataclass(frozen=True)
class SimplexQPResult:
    """Solution of :func:`solve_simplex_qp`.

    w : (N,) float64          optimal weights, ``w ≥ 0``, ``Σ w = 1`` (exactly zero off the free set)
    objective : float         ``wᵀ G w − 2 bᵀ w`` (with the ridge); add ``ãᵀ Ω ã`` for ‖D̃w − ã‖²_Ω
    iterations : int          active-set steps taken
    """

    w: np.ndarray
    objective: float
    iterations: int


def _kkt(G: np.ndarray, b: np.ndarray, P: np.ndarray) -> np.ndarray:
    """Minimizer z of ``zᵀ G_PP z − 2 b_Pᵀ z`` subject to ``Σ z = 1`` (one bordered solve)."""
    k = len(P)
    K = np.empty((k + 1, k + 1))
    K[:k, :k] = G[P[:, None], P]
    K[:k, k] = K[k, :k] = 1.0
    K[k, k] = 0.0
    rhs = np.empty(k + 1)
    rhs[:k] = b[P]
    rhs[k] = 1.0
    try:
        return np.linalg.solve(K, rhs)[:k]
    except np.linalg.LinAlgError:
        return np.linalg.lstsq(K, rhs, rcond=None)[0][:k]


def ridged(G: np.ndarray, c: float) -> np.ndarray:
    """``G + c I`` (N,N), a new array: the diagonal added to a copy of G, the same values as
    the sum with ``c · np.eye(N)`` (whose off-diagonal zeros add nothing) without making and
    adding that N×N identity (issue 23: a level-1 match, N = 630, 1.75 → 1.19 ms per region,
    with :func:`_kkt`'s submatrix gathered without ``np.ix_``)."""
    out = np.array(G, dtype=np.float64)
    out.flat[::len(out) + 1] += c
    return out


def solve_simplex_qp(G: np.ndarray, b: np.ndarray, ridge: float = QP_RIDGE, tol: float = QP_TOL,
                     max_iterations: int | None = None) -> SimplexQPResult:
    """Exact minimizer of ``wᵀ G w − 2 bᵀ w`` over ``w ≥ 0, Σ w = 1`` (bermano2014 eq. 2–3).

    Parameters
    ----------
    G : (N,N) float       symmetric positive semi-definite, e.g. ``D̃ᵀ Ω_r D̃``
    b : (N,) float        e.g. ``D̃ᵀ Ω_r ã``
    ridge : float         relative Tikhonov term (see the module docstring); 0 disables it
    tol : float           relative tolerance of the multiplier and positivity tests
    max_iterations : int | None   safeguard (default ``10 N + 100``)

    Returns
    -------
    SimplexQPResult

    Raises
    ------
    RuntimeError   the safeguard was hit (never observed)

    Notes
    -----
    Anti-cycling: a frame dropped by a step of length 0 (a degenerate vertex, frequent when
    database frames are nearly affinely dependent) may not re-enter until a step makes
    progress; the multiplier test ignores values below ``10 · ridge`` relative, the size of
    the ridge's own contribution.
    """
    G = np.asarray(G, dtype=np.float64)
    b = np.asarray(b, dtype=np.float64)
    N = len(b)
    if G.shape != (N, N):
        raise ValueError(f"G must be ({N},{N}), got {G.shape}")
    if N == 0:
        raise ValueError("need at least one column")
    scale = float(np.mean(np.abs(np.diag(G)))) or 1.0
    if ridge > 0:
        G = ridged(G, ridge * scale)
    # multipliers below this are noise (the ridge alone makes them ~ridge · scale)
    tol_mu = max(tol, 10.0 * ridge) * max(scale, float(np.max(np.abs(b))), 1e-300)
    max_iterations = 10 * N + 100 if max_iterations is None else max_iterations
    # start at the best vertex of the simplex
    j = int(np.argmin(np.diag(G) - 2.0 * b))
    free = np.zeros(N, dtype=bool)
    free[j] = True
    blocked = np.zeros(N, dtype=bool)     # dropped without progress: may not re-enter until progress
    w = np.zeros(N)
    w[j] = 1.0
    for it in range(1, max_iterations + 1):
        P = np.flatnonzero(free)
        z = _kkt(G, b, P)
        if np.all(z > tol):
            if np.max(np.abs(z - w[P])) > tol:
                blocked[:] = False                     # progress
            w[:] = 0.0
            w[P] = z
            g = G @ w - b                              # half the gradient
            # multipliers of the bounds: μ_i = g_i − g_P (g is constant on P at the optimum)
            mu = g - np.dot(w, g)                      # Σ w = 1: wᵀg is the common value on P
            mu[free | blocked] = np.inf
            i = int(np.argmin(mu))
            if mu[i] >= -tol_mu:
                return SimplexQPResult(w.copy(), float(w @ G @ w - 2.0 * b @ w), it)
            free[i] = True
        else:
            # move from w towards z until the first weight hits 0, and drop it
            d = z - w[P]
            neg = d < 0
            ratio = np.full(len(P), np.inf)
            ratio[neg] = w[P][neg] / -d[neg]
            alpha = float(min(1.0, ratio.min()))
            wP = np.maximum(w[P] + alpha * d, 0.0)
            if alpha < 1.0:
                wP[np.argmin(ratio)] = 0.0              # the blocking frame
            wP[wP <= tol] = 0.0                         # (alpha = 1: z's non-positive weights)
            w[P] = wP
            w /= w.sum()
            dropped = P[wP <= tol]
            free[dropped] = False
            if alpha > tol:
                blocked[:] = False
            else:                                       # a degenerate step: anti-cycling
                blocked[dropped] = True
            if not free.any():                          # cannot happen for Σ w = 1
                free[int(np.argmax(w))] = True
    raise RuntimeError(f"active-set simplex QP did not converge in {max_iterations} iterations")


def simplex_least_squares(D: np.ndarray, a: np.ndarray, weights: np.ndarray | None = None,
                          **kwargs) -> SimplexQPResult:
    """``argmin ‖D w − a‖²_Ω`` over the simplex for explicit vectors (D (k,N), a (k,), Ω diag (k,)).

    Convenience wrapper of :func:`solve_simplex_qp` that forms ``G = Dᵀ Ω D``, ``b = Dᵀ Ω a``.
    """
    D = np.asarray(D, dtype=np.float64)
    a = np.asarray(a, dtype=np.float64)
    Om = np.ones(len(a)) if weights is None else np.asarray(weights, dtype=np.float64)
    DO = D.T * Om
    return solve_simplex_qp(DO @ D, DO @ a, **kwargs)
