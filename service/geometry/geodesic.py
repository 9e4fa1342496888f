"""Geodesic distances on triangle meshes: the heat method, and edge-graph Dijkstra as reference.

Used for the soft region weights of bermano2014 §4.3 / §5.3 ("each mesh triangle is weighted
according to its geodesic distance from each of the regions", decaying in a Gaussian way).

Why the heat method (Crane, Weischedel & Wardetzky 2013, "Geodesics in heat", Algorithm 1)
rather than Dijkstra: Dijkstra on the edge graph is exact *for the graph*, but paths are
forced along edges, so it overestimates the surface distance by a metrication error
(≈ 5-10 % on irregular meshes, direction-dependent, never vanishing under refinement). The
heat method converges to the smooth geodesic distance as the mesh is refined, is smooth (no
direction-dependent zig-zags in its level sets — which matters once the distance goes
through a Gaussian falloff), and costs two prefactored back-substitutions per query set.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import connected_components, dijkstra

from service.geometry.deformation_gradient import GradientOperator
from service.geometry.laplacian import cotangent_laplacian, mass_matrix
from service.geometry.sparse_solve import factorize
from service.geometry.topology import adjacency_matrix, boundary_vertices, edges


def mean_edge_length(V: np.ndarray, F: np.ndarray) -> float:
    """Mean length of the unique edges of (V (n,3), F (m,3)), in units of V."""
    E, _ = edges(np.asarray(F, dtype=np.int64))
    V = np.asarray(V, dtype=np.float64)
    return float(np.linalg.norm(V[E[:, 0]] - V[E[:, 1]], axis=1).mean())


class HeatGeodesics:
    """Prefactored heat-method geodesic distance (Crane et al. 2013, Algorithm 1).

    1. heat flow ``(M - t L) u = δ_S`` for time t (one backward-Euler step),
    2. unit field ``X = -∇u / |∇u|`` per triangle,
    3. integrated divergence ``b = Dᵀ W X`` (``= -div X`` in the paper's sign),
    4. Poisson ``-L φ = b``, i.e. ∇φ ≈ X in the area-weighted least-squares sense,
    5. shift so the sources sit at 0.

    ``L`` is the cotangent Laplacian (negative semi-definite), ``M`` the lumped barycentric
    mass matrix, ``D`` the per-triangle gradient (:class:`GradientOperator`) and ``W`` the
    triangle areas. Both systems are factored once here; each :meth:`distance` query is two
    back-substitutions.

    Parameters
    ----------
    V : (n,3) float    vertices (mm)
    F : (m,3) int      triangles
    t : float | None   heat time (mm²); default the paper's ``h²`` with h the mean edge length
    boundary : ``"neumann"`` (zero-flux heat, the natural condition) or ``"average"`` (mean of
        the Neumann and Dirichlet (u = 0 on the boundary) heat solutions, Crane et al. §3.3,
        which makes level sets near the boundary less biased; one extra factorization)

    Notes
    -----
    The Poisson problem is singular (constants); it is pinned at one vertex per connected
    component, and each component is shifted by its own sources' minimum. Components without
    a source get ``inf``.

    Accuracy measured on the ICT rig (11k vertices, h = 3.9 mm) against exact polyhedral
    geodesics (MMP, libigl ``exact_geodesic``), beyond 3 edges from the source: heat median
    ratio 0.99-1.01, 1st-99th percentile 0.93-1.06; edge Dijkstra median 1.05-1.10,
    99th percentile 1.12-1.16. Within the first ring or two the heat distance is off by a
    fraction of an edge (it is smoothed at the scale √t = h).
    """

    def __init__(self, V: np.ndarray, F: np.ndarray, t: float | None = None,
                 boundary: str = "neumann"):
        V = np.asarray(V, dtype=np.float64)
        F = np.asarray(F, dtype=np.int64)
        if boundary not in ("neumann", "average"):
            raise ValueError(f"boundary must be 'neumann' or 'average', got {boundary!r}")
        n = len(V)
        self.n = n
        self.t = mean_edge_length(V, F) ** 2 if t is None else float(t)
        L = cotangent_laplacian(V, F)
        M = mass_matrix(V, F)
        self.grad = GradientOperator(V, F)
        self._DtW = (self.grad.D.T @ sp.diags(np.repeat(self.grad.areas, 3))).tocsr()
        heat = (M - self.t * L).tocsr()
        lonely = heat.diagonal() <= 0                          # vertices used by no triangle
        if lonely.any():
            heat = (heat + sp.diags(lonely.astype(np.float64))).tocsr()
        self._heat = factorize(heat, spd=True)
        self._heat_dirichlet = None
        if boundary == "average":
            bnd = boundary_vertices(F, n)
            self._interior = np.flatnonzero(~bnd)
            if len(self._interior) < n:
                self._heat_dirichlet = factorize(heat[self._interior][:, self._interior], spd=True)
        self.ncomp, self.label = connected_components(adjacency_matrix(F, n), directed=False)
        first = np.full(self.ncomp, n)
        np.minimum.at(first, self.label, np.arange(n))
        self._pin = first
        free = np.ones(n, dtype=bool)
        free[first] = False
        self._free = np.flatnonzero(free)
        K = (-L).tocsr()
        self._poisson = factorize(K[self._free][:, self._free], spd=True)

    def distance(self, sources: np.ndarray) -> np.ndarray:
        """Geodesic distance (n,) from the nearest of the given source vertices, mm.

        Parameters
        ----------
        sources : (s,) int   source vertex indices (one set; the distance is to the set)

        Returns
        -------
        d : (n,) float64   0 at (the closest) sources, ``inf`` in components without one
        """
        src = np.unique(np.asarray(sources, dtype=np.int64).ravel())
        if len(src) == 0:
            raise ValueError("at least one source vertex is required")
        delta = np.zeros(self.n)
        delta[src] = 1.0
        u = self._heat(delta)
        if self._heat_dirichlet is not None:
            ud = np.zeros(self.n)
            ud[self._interior] = self._heat_dirichlet(delta[self._interior])
            u = 0.5 * (u + ud)
        g = (self.grad.D @ u).reshape(-1, 3)                    # (m,3) ∇u per triangle
        norm = np.linalg.norm(g, axis=1, keepdims=True)
        X = -g / np.where(norm > 0, norm, 1.0)
        b = self._DtW @ X.ravel()
        phi = np.zeros(self.n)
        phi[self._free] = self._poisson(b[self._free])
        shift = np.full(self.ncomp, np.inf)
        np.minimum.at(shift, self.label[src], phi[src])
        d = phi - shift[self.label]
        d[~np.isfinite(shift[self.label])] = np.inf
        return d

    __call__ = distance


def geodesic_distance(V: np.ndarray, F: np.ndarray, sources: np.ndarray,
                      t: float | None = None) -> np.ndarray:
    """Heat-method geodesic distance (n,) from a set of source vertices (one-shot).

    See :class:`HeatGeodesics` (keep that object for several queries on one mesh).

    Parameters
    ----------
    V : (n,3) float   vertices (mm)
    F : (m,3) int     triangles
    sources : (s,) int

    Returns
    -------
    d : (n,) float64, mm
    """
    return HeatGeodesics(V, F, t=t).distance(sources)


def edge_dijkstra_distance(V: np.ndarray, F: np.ndarray, sources: np.ndarray) -> np.ndarray:
    """Shortest-path distance (n,) along mesh edges from the nearest source (reference).

    Exact on the edge graph (``scipy.sparse.csgraph.dijkstra``), an upper bound of the
    surface geodesic distance: see the module docstring for the metrication error.

    Parameters
    ----------
    V : (n,3) float   vertices (mm)
    F : (m,3) int     triangles
    sources : (s,) int

    Returns
    -------
    d : (n,) float64, mm; ``inf`` where unreachable
    """
    V = np.asarray(V, dtype=np.float64)
    E, _ = edges(np.asarray(F, dtype=np.int64))
    w = np.linalg.norm(V[E[:, 0]] - V[E[:, 1]], axis=1)
    n = len(V)
    G = sp.csr_matrix((w, (E[:, 0], E[:, 1])), shape=(n, n))
    src = np.unique(np.asarray(sources, dtype=np.int64).ravel())
    return dijkstra(G, directed=False, indices=src, min_only=True)
