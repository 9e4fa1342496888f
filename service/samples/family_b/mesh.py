"""Family b's skin mesh: the rig's quads cut the other way, refined adaptively, reordered.

Built from the ICT rig's topology only (positions come later, through the linear operator
``S``), so that every rig pose maps to the high-resolution surface as ``S @ pose``:

1. every quad (a,b,c,d) is split along the *other* diagonal, (a,b,d), (b,c,d) (the rig and
   family a split it as (a,b,c), (a,c,d));
2. **red-green refinement** (Bank, Sherman & Weiser 1983): the triangles marked red are
   split 1→4; a triangle with two or three split edges is made red too (repeated until
   stable), and a triangle with exactly one split edge is bisected (green), so the mesh stays
   conforming while its density varies — the face gets more vertices per mm² than the
   head, and the narrow face (eyes, mouth, nose) more again;
3. new edge vertices are placed by the **modified butterfly** stencil (Dyn, Levin & Gregory
   1990; weights 1/2, 1/8, −1/16, w = 1/16), which interpolates the coarse vertices (the
   rig's vertices do not move, unlike Loop's even rule used by family a); an edge whose
   stencil touches the boundary takes the midpoint;
4. the vertices are renumbered in a spatial order (4 mm cells, top to bottom, then left to
   right, then back to front) and the triangles by their first vertex, so no vertex range
   corresponds to the rig's vertices.

UVs are per corner and refined by midpoints (charts are piecewise linear).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

from service.geometry.topology import edges

ORDER_CELL_MM = 4.0


@dataclass(frozen=True)
class RefinedMesh:
    """A refined mesh as operators on the coarse one.

    Attributes
    ----------
    S : (n,n0) sparse CSR        fine positions = ``S @ coarse positions``
    faces : (m,3) int            fine triangles
    S_uv : (K,K0) sparse CSR     fine UVs = ``S_uv @ coarse UVs``
    uv_faces : (m,3) int
    region : (n,) int            coarse region carried to the fine vertices (max over the
                                 endpoints of the edge a vertex was born on)
    """

    S: sp.csr_matrix
    faces: np.ndarray
    S_uv: sp.csr_matrix
    uv_faces: np.ndarray
    region: np.ndarray


def flip_quad_diagonals(triangles: np.ndarray) -> np.ndarray:
    """Re-split quads stored as triangle pairs (a,b,c), (a,c,d) into (a,b,d), (b,c,d).

    Parameters
    ----------
    triangles : (2q,3) int   rows 2i and 2i+1 are quad i split along a–c

    Returns
    -------
    (2q,3) int, the same quads split along b–d (orientation kept)
    """
    T = np.asarray(triangles, np.int64)
    first, second = T[0::2], T[1::2]
    if not (np.array_equal(first[:, 0], second[:, 0]) and np.array_equal(first[:, 2], second[:, 1])):
        raise ValueError("triangles are not quads split as (a,b,c), (a,c,d) in consecutive rows")
    a, b, c, d = first[:, 0], first[:, 1], first[:, 2], second[:, 2]
    out = np.empty_like(T)
    out[0::2] = np.stack([a, b, d], axis=1)
    out[1::2] = np.stack([b, c, d], axis=1)
    return out


def red_closure(F: np.ndarray, red: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Close a red set: triangles with ≥ 2 split edges become red until stable.

    Returns
    -------
    red : (m,) bool            closed red set
    split : (e,) bool          edges split (the red triangles' edges)
    E, corner_edge             :func:`~service.geometry.topology.edges` of F
    """
    E, corner_edge = edges(F)
    red = np.asarray(red, bool).copy()
    while True:
        split = np.zeros(len(E), bool)
        split[corner_edge[red].ravel()] = True
        grow = split[corner_edge].sum(axis=1) >= 2
        if not (grow & ~red).any():
            return red, split, E, corner_edge
        red |= grow


def _new_ids(split: np.ndarray, n: int) -> np.ndarray:
    ids = np.full(len(split), -1, np.int64)
    ids[split] = n + np.arange(int(split.sum()))
    return ids


def _split(F: np.ndarray, corner_edge: np.ndarray, ids: np.ndarray, red: np.ndarray,
           split: np.ndarray) -> np.ndarray:
    """Triangles after splitting: red 1→4, green (one split edge) 1→2, others kept."""
    mid = ids[corner_edge]                                  # (m,3) new vertex opposite each corner, or -1
    a, b, c = F[red, 0], F[red, 1], F[red, 2]
    m_bc, m_ca, m_ab = mid[red, 0], mid[red, 1], mid[red, 2]
    red_tris = np.concatenate([np.stack(t, axis=1) for t in (
        (a, m_ab, m_ca), (m_ab, b, m_bc), (m_ca, m_bc, c), (m_ab, m_bc, m_ca))])
    count = split[corner_edge].sum(axis=1)
    green = (count == 1) & ~red
    k = np.argmax(split[corner_edge[green]], axis=1)        # corner opposite the split edge
    G = F[green]
    rot = np.stack([G[np.arange(len(G)), (k + j) % 3] for j in range(3)], axis=1)   # split edge = (1,2)
    m = mid[green][np.arange(len(G)), k]
    green_tris = np.concatenate([np.stack([rot[:, 0], rot[:, 1], m], axis=1),
                                 np.stack([rot[:, 0], m, rot[:, 2]], axis=1)])
    return np.concatenate([F[~red & ~green], red_tris, green_tris]).astype(np.int64)


def butterfly_operator(F: np.ndarray, E: np.ndarray, corner_edge: np.ndarray,
                       split: np.ndarray, n: int) -> sp.csr_matrix:
    """(n+s, n) operator: identity on the coarse vertices, modified butterfly on split edges.

    For edge (i,j) with opposite vertices k, l and the four wing vertices across the other
    edges of its two triangles: ``½(i+j) + ⅛(k+l) − 1⁄16 Σ wings``; the midpoint where the
    edge or any stencil edge lies on the boundary.
    """
    m = len(F)
    inc = np.bincount(corner_edge.ravel(), minlength=len(E))         # triangles per edge
    opp_sum = sp.csr_matrix((np.ones(3 * m), (corner_edge.ravel(), F.ravel())), shape=(len(E), n))
    rows, cols, vals = [], [], []
    # per (triangle, corner k): edge e opposite k, with the triangle's other edges e1, e2
    t = np.repeat(np.arange(m), 3)
    k = np.tile(np.arange(3), m)
    e = corner_edge[t, k]
    e1, e2 = corner_edge[t, (k + 1) % 3], corner_edge[t, (k + 2) % 3]
    interior = (inc[e] == 2) & (inc[e1] == 2) & (inc[e2] == 2)
    full = np.zeros(len(E), bool)
    full[e] = True
    np.logical_and.at(full, e, interior)                               # both triangles' stencils complete
    sel = split[e] & full[e]
    # opposite vertex k: 1/8; wing across e1 (opposite corner (k+1)%3 in t) = opp_sum[e1] − F[t,(k+1)%3]
    rows.append(e[sel]); cols.append(F[t[sel], k[sel]]); vals.append(np.full(sel.sum(), 1 / 8))
    for edge, corner in ((e1, (k + 1) % 3), (e2, (k + 2) % 3)):
        W = opp_sum[edge[sel]].tocoo()
        rows.append(e[sel][W.row]); cols.append(W.col); vals.append(-W.data / 16)
        rows.append(e[sel]); cols.append(F[t[sel], corner[sel]]); vals.append(np.full(sel.sum(), 1 / 16))
    S_edge = sp.csr_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))),
                           shape=(len(E), n))
    mid = sp.csr_matrix((np.full(2 * len(E), 0.5), (np.repeat(np.arange(len(E)), 2), E.ravel())),
                        shape=(len(E), n))
    S_edge = (mid + sp.diags(full.astype(float)) @ S_edge)[split]
    return sp.vstack([sp.identity(n, format="csr"), S_edge]).tocsr()


def refine(F: np.ndarray, n: int, UF: np.ndarray, K: int, region: np.ndarray,
           red: np.ndarray) -> RefinedMesh:
    """One red-green pass over triangles ``red`` (m,) bool; see the module docstring."""
    F, UF = np.asarray(F, np.int64), np.asarray(UF, np.int64)
    red, split, E, corner_edge = red_closure(F, red)
    ids = _new_ids(split, n)
    S = butterfly_operator(F, E, corner_edge, split, n)
    # UV edges are split where their geometric edge is
    E_uv, ce_uv = edges(UF)
    split_uv = np.zeros(len(E_uv), bool)
    split_uv[ce_uv[split[corner_edge]]] = True
    ids_uv = _new_ids(split_uv, K)
    S_uv = sp.vstack([sp.identity(K, format="csr"),
                      sp.csr_matrix((np.full(2 * split_uv.sum(), 0.5),
                                     (np.repeat(np.arange(split_uv.sum()), 2), E_uv[split_uv].ravel())),
                                    shape=(int(split_uv.sum()), K))]).tocsr()
    faces = _split(F, corner_edge, ids, red, split)
    uv_faces = _split(UF, ce_uv, ids_uv, red, split_uv)
    region = np.concatenate([region, np.maximum(region[E[split, 0]], region[E[split, 1]])])
    return RefinedMesh(S, faces, S_uv, uv_faces, region)


def compose(a: RefinedMesh, b: RefinedMesh) -> RefinedMesh:
    """Refinement ``b`` applied after ``a`` (b's operators act on a's fine mesh)."""
    return RefinedMesh((b.S @ a.S).tocsr(), b.faces, (b.S_uv @ a.S_uv).tocsr(), b.uv_faces, b.region)


def spatial_order(V: np.ndarray, cell: float = ORDER_CELL_MM) -> np.ndarray:
    """Permutation (n,) listing vertices by 4 mm cells: top to bottom, left to right, back to front."""
    q = np.floor(np.asarray(V) / cell).astype(np.int64)
    return np.lexsort((q[:, 2], q[:, 0], -q[:, 1]))


def reorder(mesh: RefinedMesh, order: np.ndarray) -> RefinedMesh:
    """Renumber vertices so that new vertex i is old vertex ``order[i]``; triangles by first vertex."""
    rank = np.empty_like(order)
    rank[order] = np.arange(len(order))
    faces = rank[mesh.faces]
    tri = np.argsort(faces.min(axis=1), kind="stable")
    return RefinedMesh(mesh.S[order].tocsr(), faces[tri], mesh.S_uv, mesh.uv_faces[tri],
                       mesh.region[order])
