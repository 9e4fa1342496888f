"""Per-vertex feature-edge weights and weighted feature distances of WPSD (bickel2008 §5.3).

Eq. 4: for vertex v and feature edge i with rest endpoints p_i1, p_i2 and rest length l_i,

    ᾱ_v,i = exp(−β (L_v,i − l_i)),   L_v,i = ‖v − p_i1‖ + ‖v − p_i2‖,
    α_v,i = ᾱ_v,i / Σ_i ᾱ_v,i,

1 on the edge and decaying on confocal ellipses around it. As in the paper, weights
ᾱ < ``threshold`` (0.025) are discarded and at most ``max_edges`` (16) edges influence a
vertex. β: "based on the local density of handle vertices ... such that a vertex is
influenced by at most 16 edges" — by default it is set **per vertex**, β_v = ln(1/threshold)
/ e_(k+1),v with e_(k+1),v the (k+1)-th smallest excess L_v,i − l_i, so exactly k edges keep
ᾱ ≥ threshold everywhere (dense markers: sharp decay, sparse: wide). A global β may be given
instead. Distances are Euclidean in the rest pose.

Eq. 3, the weighted feature distance of vertex v to pose j,

    ‖f − f_j‖_v² = Σ_i α_v,i (f_i − f_j,i)²,

is one sparse product ``A @ (f − f_j)²`` for all vertices and poses, with α stored as a
CSR matrix A (n,E) (§6.2: "α_v,i is represented as a sparse matrix").
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from service.methods.pose_space.feature_graph import FeatureGraph

#: vertices per chunk of the dense (chunk, E) excess matrix
CHUNK = 4096


def edge_weights(vertices: np.ndarray, nodes: np.ndarray, graph: FeatureGraph,
                 threshold: float = 0.025, max_edges: int = 16,
                 beta: float | None = None) -> sp.csr_matrix:
    """α (eq. 4) of every vertex for every feature edge, sparse.

    Parameters
    ----------
    vertices : (n,3) float   rest-pose vertices, mm
    nodes : (N,3) float      rest positions of the graph's nodes (the markers), mm
    graph : FeatureGraph     edges over the nodes and rest lengths
    threshold : float        discard ᾱ below this
    max_edges : int          keep at most this many edges per vertex (the largest ᾱ)
    beta : float or None     global decay, 1/mm; None: per vertex (module docstring)

    Returns
    -------
    A : (n,E) CSR float64   rows sum to 1; between 1 and ``max_edges`` entries per row (a
                            vertex whose every ᾱ is below the threshold keeps its nearest
                            edge)
    """
    V = np.asarray(vertices, dtype=np.float64)
    P1, P2 = nodes[graph.edges[:, 0]], nodes[graph.edges[:, 1]]
    E, n = graph.n_edges, len(V)
    k = min(max_edges, E)
    log_t = np.log(1.0 / threshold)
    floor = 1e-9 * float(np.median(graph.rest_length))
    rows, cols, vals = [], [], []
    for s in range(0, n, CHUNK):
        X = V[s:s + CHUNK]
        L = (np.linalg.norm(X[:, None] - P1[None], axis=2) + np.linalg.norm(X[:, None] - P2[None], axis=2))
        e = np.maximum(L - graph.rest_length, 0.0)                              # (c,E) excess
        idx = np.argpartition(e, k - 1, axis=1)[:, :k] if k < E else np.tile(np.arange(E), (len(X), 1))
        ek = np.take_along_axis(e, idx, axis=1)                                 # (c,k)
        if beta is None:
            nxt = np.partition(e, k, axis=1)[:, k] if k < E else ek.max(axis=1) + floor
            b = log_t / np.maximum(nxt, floor)
        else:
            b = np.full(len(X), float(beta))
        abar = np.exp(-b[:, None] * ek)
        keep = abar >= threshold
        nearest = np.argmin(ek, axis=1)
        keep[np.arange(len(X)), nearest] = True
        abar = np.where(keep, abar, 0.0)
        # a vertex whose ᾱ all underflow keeps its nearest edge alone
        tot = abar.sum(axis=1)
        lone = ~(tot > 0)
        abar[lone, nearest[lone]] = 1.0
        alpha = abar / abar.sum(axis=1, keepdims=True)
        r, c = np.nonzero(keep)
        rows.append(r + s)
        cols.append(idx[r, c])
        vals.append(alpha[r, c])
    A = sp.csr_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))), shape=(n, E))
    A.sort_indices()
    return A


def equal_weights(n: int, E: int) -> sp.csr_matrix:
    """α_v,i = 1/E for every vertex and edge: eq. 3 becomes the global ‖f − f_j‖²/E of PSD."""
    return sp.csr_matrix(np.full((n, E), 1.0 / E))


def weighted_sq_distances(A: sp.csr_matrix, f: np.ndarray, basis: np.ndarray) -> np.ndarray:
    """‖f − f_j‖_v² (eq. 3) of every vertex v to every basis pose j.

    Parameters
    ----------
    A : (n,E) sparse      edge weights α (:func:`edge_weights`)
    f : (E,) or (T,E)     feature vector(s) of the evaluated pose(s)
    basis : (P,E)         feature vectors f_j of the basis poses

    Returns
    -------
    D2 : (n,P) or (n,T,P) float64   non-negative
    """
    f = np.asarray(f, dtype=np.float64)
    G = (f[..., None, :] - basis) ** 2                                          # (…,P,E)
    if f.ndim == 1:
        return np.asarray(A @ G.T)
    T, P = G.shape[:2]
    return np.asarray(A @ G.reshape(T * P, -1).T).reshape(A.shape[0], T, P)
