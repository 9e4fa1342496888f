"""Prefactored sparse linear solves: factor ``A`` once, solve for many right-hand sides.

Every implicit step of the numerical core (the thin shell of bickel2008 §4, Poisson
reconstruction, implicit curvature flow, heat-method geodesics) solves the same sparse
matrix against many right-hand sides, so the factorization is done once per actor and
kept in a :class:`Factor`.

Backend choice
--------------
SciPy has no sparse Cholesky, and scikit-sparse (CHOLMOD) is not a dependency, so this
module uses SuperLU (``scipy.sparse.linalg.splu``). For symmetric positive-definite
matrices (``spd=True``, the default) it is driven as a Cholesky substitute: a symmetric
fill-reducing ordering (multiple minimum degree on the pattern of A + Aᵀ,
``permc_spec="MMD_AT_PLUS_A"``), ``SymmetricMode`` so the row permutation equals the
column permutation, and ``diag_pivot_thresh=0`` (always pivot on the diagonal: no row
interchanges, which keep the symmetric ordering intact; elimination without pivoting is
backward stable for SPD matrices, as in Cholesky). Measured on the thin-shell
matrix of the ICT face (bi-Laplacian stencil) against SuperLU's default COLAMD with
partial pivoting:

===========  ======================  ==================  ============
mesh         ordering                factorization       fill nnz(L+U)
===========  ======================  ==================  ============
11 k verts   COLAMD, partial pivot   0.37 s              2.9 M
11 k verts   MMD(A+Aᵀ), symmetric    0.23 s              2.1 M
45 k verts   COLAMD, partial pivot   2.9 s               17.6 M
45 k verts   MMD(A+Aᵀ), symmetric    1.2–1.5 s           11.9 M
179 k verts  MMD(A+Aᵀ), symmetric    21 s                67.5 M
===========  ======================  ==================  ============

and the triangular solves are 2–3× faster with the smaller factor. General (unsymmetric
or indefinite) matrices use ``spd=False``: COLAMD with SuperLU's default partial pivoting.

For the per-frame solves of a hot loop, ``backend="cholmod"`` factors an SPD matrix with
CHOLMOD's supernodal Cholesky (the ``cholespy`` wheel, which bundles SuiteSparse). On the
179k-vertex curvature-flow matrix of the level-2 sample actor it factors in 2.3 s (SuperLU
~20 s) and solves three right-hand sides in 0.031 s against SuperLU's 0.127 s, equal to
5e-15. CHOLMOD accepts a singular positive semi-definite matrix without complaint, so the
factorization is checked by the residual of one seeded solve (:data:`CHOLMOD_RTOL`).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

#: A factor whose smallest pivot is below ``PIVOT_RTOL * max |pivot|`` is treated as
#: singular. Measured pivot ratios of the thin-shell system (150 handles) on the ICT face:
#: 6e-7 (11 k vertices), 2e-8 (45 k), 4e-10 (179 k); a singular PSD matrix (the same
#: operator without handles) gives 1e-16.
PIVOT_RTOL = 1e3 * np.finfo(np.float64).eps
#: a CHOLMOD factor whose seeded check solve leaves a relative residual above this is
#: treated as singular (a singular PSD Laplacian gives ~1; the SPD systems here ~1e-15)
CHOLMOD_RTOL = 1e-8
#: factor entries (of FACTOR_ENTRY_BYTES) per nonzero of A that a CHOLMOD factor of a
#: triangle-mesh Laplacian holds: CHOLMOD does not report its fill; measured 110 and 103
#: bytes per nonzero on the level-1 and level-2 sample actors' curvature-flow matrices
CHOLMOD_FILL_PER_NNZ = 9


@dataclass(frozen=True)
class Factor:
    """A sparse LU factorization ready for repeated solves; call it like :meth:`solve`.

    Attributes
    ----------
    n : int              order of the factored matrix
    spd : bool           factored as symmetric positive-definite (no pivoting)
    fill : int           nnz(L) + nnz(U), a proxy for the factor's memory (12 bytes each);
                         for the CHOLMOD backend estimated (:data:`CHOLMOD_FILL_PER_NNZ`)
    pivot_ratio : float  min |pivot| / max |pivot|, a cheap singularity indicator (NaN for
                         the CHOLMOD backend, whose check is a residual)
    """

    n: int
    spd: bool
    fill: int
    pivot_ratio: float
    _lu: spla.SuperLU | None = field(repr=False)
    _chol: object = field(default=None, repr=False)       # cholespy.CholeskySolverD

    def solve(self, b: np.ndarray) -> np.ndarray:
        """Solve ``A x = b``.

        Parameters
        ----------
        b : (n,) or (n,k) float   right-hand side(s); any float dtype, computed in float64

        Returns
        -------
        x : same shape as ``b``, float64
        """
        b = np.asarray(b, dtype=np.float64)
        if b.shape[:1] != (self.n,) or b.ndim > 2:
            raise ValueError(f"right-hand side must be ({self.n},) or ({self.n},k), got {b.shape}")
        if b.ndim == 2 and b.shape[1] == 0:
            return np.zeros_like(b)
        if self._chol is not None:
            b = np.ascontiguousarray(b)
            x = np.zeros_like(b)
            self._chol.solve(b, x)
            return x
        return self._lu.solve(np.asfortranarray(b))

    __call__ = solve


def factorize(A: sp.spmatrix | sp.sparray, spd: bool = True, backend: str = "superlu") -> Factor:
    """Factor a square sparse matrix once for repeated solves.

    Parameters
    ----------
    A : (n,n) sparse     any SciPy sparse format; converted to CSC float64
    spd : bool           ``True`` if A is symmetric positive-definite (Laplacian-type
                         systems with constraints, mass + t·stiffness, the thin shell):
                         symmetric minimum-degree ordering, diagonal pivots. ``False`` for
                         general matrices: COLAMD with partial pivoting.
    backend : "superlu" | "cholmod"   "cholmod" (SPD only): CHOLMOD's supernodal Cholesky,
                         ~4× faster solves for the per-frame loops (see the module docstring)

    Returns
    -------
    Factor
        ``factor(b)`` / ``factor.solve(b)`` solves ``A x = b`` for (n,) or (n,k) ``b``.

    Raises
    ------
    ValueError
        A is not square, or contains non-finite entries.
    numpy.linalg.LinAlgError
        A is (numerically) singular: a zero pivot, or ``pivot_ratio < PIVOT_RTOL``.

    Notes
    -----
    With ``spd=True`` symmetry is assumed, not checked (checking costs as much as a
    sparse transpose-and-compare; callers build their matrices symmetric by construction).
    """
    A = sp.csc_matrix(A, dtype=np.float64)
    if A.shape[0] != A.shape[1]:
        raise ValueError(f"matrix must be square, got {A.shape}")
    if not np.all(np.isfinite(A.data)):
        raise ValueError("matrix has non-finite entries")
    A.sum_duplicates()
    A.sort_indices()
    if backend not in ("superlu", "cholmod"):
        raise ValueError(f"backend must be 'superlu' or 'cholmod', got {backend!r}")
    if backend == "cholmod":
        if not spd:
            raise ValueError("the cholmod backend factors symmetric positive-definite matrices only")
        return _cholmod(A)
    if spd:
        kwargs = dict(permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.0,
                      options=dict(SymmetricMode=True))
    else:
        kwargs = dict(permc_spec="COLAMD")
    try:
        lu = spla.splu(A, **kwargs)
    except RuntimeError as exc:  # SuperLU: "Factor is exactly singular"
        raise np.linalg.LinAlgError(f"sparse matrix of order {A.shape[0]} is singular: {exc}") from None
    pivots = np.abs(lu.U.diagonal())
    ratio = float(pivots.min() / pivots.max()) if len(pivots) else 1.0
    if not np.isfinite(ratio) or ratio < PIVOT_RTOL:
        raise np.linalg.LinAlgError(
            f"sparse matrix of order {A.shape[0]} is numerically singular "
            f"(pivot ratio {ratio:.1e} < {PIVOT_RTOL:.1e})"
        )
    return Factor(n=A.shape[0], spd=spd, fill=int(lu.L.nnz + lu.U.nnz), pivot_ratio=ratio, _lu=lu)


def _cholmod(A: sp.csc_matrix) -> Factor:
    """CHOLMOD factor of an SPD matrix, checked by one seeded solve (see :func:`factorize`)."""
    from cholespy import CholeskySolverD, MatrixType

    n = A.shape[0]
    coo = A.tocoo()
    try:
        chol = CholeskySolverD(n, coo.row.astype(np.int32), coo.col.astype(np.int32),
                               coo.data.astype(np.float64), MatrixType.COO)
    except ValueError as exc:                  # "Matrix is not positive definite!"
        raise np.linalg.LinAlgError(f"sparse matrix of order {n} is not positive definite: {exc}") from None
    factor = Factor(n=n, spd=True, fill=CHOLMOD_FILL_PER_NNZ * int(A.nnz), pivot_ratio=float("nan"),
                    _lu=None, _chol=chol)
    b = np.random.default_rng(0).standard_normal(n)
    residual = float(np.linalg.norm(A @ factor.solve(b) - b) / np.linalg.norm(b))
    if not residual <= CHOLMOD_RTOL:
        raise np.linalg.LinAlgError(f"sparse matrix of order {n} is numerically singular "
                                    f"(check residual {residual:.1e} > {CHOLMOD_RTOL:.1e})")
    return factor
