"""The per-frame WPSD correction of every vertex (bickel2008 §5.3 eq. 3 and 5, with the linear
polynomial term of :mod:`.polynomial`), compiled (Numba, ``nogil``):

    D²_v,j = Σ_{i ∈ S_v} α_v,i (f_i − f_j,i)²                          (eq. 3)
    c_v    = κ · ( Σ_j w_v,j φ(D_v,j) + c⁰_v + Σ_{i ∈ S_v} a_v,i f_i )   (eq. 5 + polynomial)

for one frame's features f (E,), the basis poses' features f_j (P,E), the vertex's edge
weights α_v (eq. 4) over its support S_v (≤ ``max_edges_per_vertex`` edges), its RBF weights
w_v (3,P), and the frame's confidence fade κ (:mod:`.model`). φ(r) = r (:func:`.rbf.kernel`).

The α matrix and the polynomial's linear coefficients share the support S_v
(:func:`.polynomial.support_index`), so they are stored here on one CSR pattern
(:func:`aligned_support`): per stored entry the edge index, α and the three coefficients —
what the SciPy form reads as two matrices (α (n,E) and the polynomial (3n,E), its
indices three times) is read once per frame, and the distances never leave the vertex
unless the fine map needs them (``D2`` out).

The sums run in float32, the stored precision of α and the weights (within 1e-5 mm of the
float64 sums, tests).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
from numba import njit, uint64

from service.geometry import ranges

FASTMATH = {"reassoc", "contract"}


#: the distances are summed in blocks of this many basis poses (G padded with zero columns
#: to a multiple of it), each block in that many scalar accumulators the compiler keeps in
#: registers (one vector), where a loop over P would load and store the sums per entry
LANES = 8


@njit(nogil=True, cache=True, fastmath=FASTMATH, error_model="numpy")
def correction_sums(lo, hi, ptr, edge, values, const, W, G, f, fade, D2, given, C):
    """Vertices [lo, hi) (rows of the CSR ``ptr``/``edge``): corrections C (3,n) float32 of
    the module docstring. ``values`` (nnz,4) holds α and the three polynomial
    coefficients of every stored entry (zeros without a polynomial); ``G`` (E,Pp)
    (f − f_j)² per edge, Pp = P padded to a multiple of :data:`LANES` with zero columns.
    With ``given`` the distances are read from D2 (n,P) instead of summed (and written to
    D2 where it has rows otherwise). ``const`` (n,3) has no rows without a polynomial.

    One pass over a vertex's entries sums the polynomial and the first :data:`LANES`
    distances; further blocks of distances (P > LANES) take one more pass each. Vertices and
    entries are indexed by unsigned integers (``ptr`` uint64, ``edge`` uint32): Numba checks
    every signed index for a negative value to wrap, which cost ~40 % of this loop."""
    P = W.shape[2]
    Pp = G.shape[1]
    has_poly = const.shape[0] > 0
    keep = D2.shape[0] > 0 and not given
    d2 = np.zeros(Pp, np.float32)
    one = uint64(1)
    for v in range(uint64(lo), uint64(hi)):
        p0, p1 = ptr[v], ptr[v + one]
        s0 = s1 = s2 = s3 = s4 = s5 = s6 = s7 = np.float32(0.0)
        px = py = pz = np.float32(0.0)
        for q in range(p0, p1):
            a = values[q, 0]
            i = edge[q]
            fi = f[i]
            px += values[q, 1] * fi
            py += values[q, 2] * fi
            pz += values[q, 3] * fi
            s0 += a * G[i, 0]
            s1 += a * G[i, 1]
            s2 += a * G[i, 2]
            s3 += a * G[i, 3]
            s4 += a * G[i, 4]
            s5 += a * G[i, 5]
            s6 += a * G[i, 6]
            s7 += a * G[i, 7]
        if given:
            for j in range(P):
                d2[j] = D2[v, j]
        else:
            d2[0], d2[1], d2[2], d2[3], d2[4], d2[5], d2[6], d2[7] = s0, s1, s2, s3, s4, s5, s6, s7
            for b in range(LANES, Pp, LANES):
                s0 = s1 = s2 = s3 = s4 = s5 = s6 = s7 = np.float32(0.0)
                for q in range(p0, p1):
                    a = values[q, 0]
                    g = G[edge[q]]
                    s0 += a * g[b]
                    s1 += a * g[b + 1]
                    s2 += a * g[b + 2]
                    s3 += a * g[b + 3]
                    s4 += a * g[b + 4]
                    s5 += a * g[b + 5]
                    s6 += a * g[b + 6]
                    s7 += a * g[b + 7]
                d2[b], d2[b + 1], d2[b + 2], d2[b + 3] = s0, s1, s2, s3
                d2[b + 4], d2[b + 5], d2[b + 6], d2[b + 7] = s4, s5, s6, s7
            if keep:
                for j in range(P):
                    D2[v, j] = d2[j]
        cx = cy = cz = np.float32(0.0)
        for j in range(P):
            r = np.sqrt(max(d2[j], np.float32(0.0)))
            cx += W[v, 0, j] * r
            cy += W[v, 1, j] * r
            cz += W[v, 2, j] * r
        if has_poly:
            cx += const[v, 0] + px
            cy += const[v, 1] + py
            cz += const[v, 2] + pz
        C[0, v] = cx * fade
        C[1, v] = cy * fade
        C[2, v] = cz * fade


@dataclass(frozen=True)
class CorrectionSum:
    """α, the polynomial and the RBF weights of a WPSD model on one CSR pattern, rows in a
    given vertex order (:func:`aligned_support`); :meth:`__call__` evaluates one frame.

    ptr (n+1,) uint64, edge (nnz,) uint32, values (nnz,4) float32 (α and the polynomial's three
    coefficients; zero coefficients without a polynomial), const (n,3) float32 (no rows
    without a polynomial), weights (n,3,P) float32, basis_features (P,E).
    """

    ptr: np.ndarray
    edge: np.ndarray
    values: np.ndarray
    const: np.ndarray
    weights: np.ndarray
    basis_features: np.ndarray

    @classmethod
    def build(cls, alpha: sp.csr_matrix, weights: np.ndarray, basis_features: np.ndarray,
              poly_const: np.ndarray | None = None, poly_linear: sp.csr_matrix | None = None,
              order: np.ndarray | None = None) -> "CorrectionSum":
        """From the stored α (n,E), weights (n,P,3), basis features (P,E) and polynomial
        (const (n,3), linear (3n,E) with row 3v + c), vertices permuted to ``order`` (n,)
        (row k holds vertex order[k]; default the identity)."""
        n = alpha.shape[0]
        order = np.arange(n) if order is None else np.asarray(order, np.int64)
        ptr, edge, values = aligned_support(alpha, poly_linear, order)
        W = np.ascontiguousarray(np.asarray(weights, np.float32)[order].transpose(0, 2, 1))
        const = (np.ascontiguousarray(np.asarray(poly_const, np.float32)[order]) if poly_linear is not None
                 else np.empty((0, 3), np.float32))
        return cls(ptr.astype(np.uint64), edge.astype(np.uint32), values, const, W,
                   np.asarray(basis_features, np.float64))

    @property
    def n_vertices(self) -> int:
        return len(self.ptr) - 1

    def __call__(self, f: np.ndarray, fade: float = 1.0, D2: np.ndarray | None = None,
                 keep_distances: bool = False, threads: int | None = None):
        """Corrections C (3,n) float32 (rows in this sum's vertex order) of one frame's
        features f (E,), faded by κ = ``fade``; the squared distances D2 (n,P) are summed
        here (eq. 3) unless given. With ``keep_distances`` returns (C, D2)."""
        n, P = self.n_vertices, self.weights.shape[2]
        f = np.asarray(f, np.float64)
        Pp = -(-P // LANES) * LANES
        G = np.zeros((len(f), Pp), np.float32)                                   # (E,Pp)
        G[:, :P] = ((f[None, :] - self.basis_features) ** 2).T
        given = D2 is not None
        if given:
            D = np.ascontiguousarray(D2, np.float32)
        else:
            D = np.empty((n, P), np.float32) if keep_distances else np.empty((0, P), np.float32)
        C = np.empty((3, n), np.float32)
        ranges.run(correction_sums, n, self.ptr, self.edge, self.values, self.const, self.weights, G, f.astype(np.float32), np.float32(fade), D, given, C,
                   threads=threads)
        return (C, D) if keep_distances else C


def aligned_support(alpha: sp.csr_matrix, poly_linear: sp.csr_matrix | None,
                    order: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """α (n,E) and the polynomial's linear coefficients (3n,E), row 3v + c, on one CSR
    pattern with rows permuted to ``order``: the union of their supports per vertex.

    Returns ptr (n+1,) int64, edge (nnz,) int64 (ascending within a row) and values
    (nnz,4) float32 = (α, a_x, a_y, a_z), zero where a matrix has no entry (each entry one
    16-byte record, read once per vertex and frame).
    """
    A = sp.csr_matrix(alpha)
    n, E = A.shape
    mats = [A]
    if poly_linear is not None:
        L = sp.csr_matrix(poly_linear)
        mats += [L[c::3] for c in range(3)]
    pattern = sum(abs(M).astype(np.float64) for M in mats)
    pattern = sp.csr_matrix(pattern)[order]
    pattern.sort_indices()
    ptr = pattern.indptr.astype(np.int64)
    rows = np.repeat(np.arange(n), np.diff(ptr))
    edge = pattern.indices.astype(np.int64)
    key = rows * E + edge                                                   # ascending
    rank = np.empty(n, np.int64)
    rank[order] = np.arange(n)
    values = np.zeros((len(edge), 4), np.float32)
    for k, M in enumerate(mats):
        M = sp.coo_matrix(M)
        M.eliminate_zeros()                                                 # only entries of the pattern
        at = np.searchsorted(key, rank[M.row] * E + M.col)
        values[at, k] = M.data
    return ptr, edge, values
