"""The voluntary regions of bermano2014 §4.3 and their soft per-triangle weights (§5.3, Figure 4).

The paper matches four voluntary regions independently — left and right halves of the
mouth, left and right eyebrows, from the 13 motion-correlation regions of Tena et al.
2011 — and weights every triangle by region: "constant within the region, and decay in a
Gaussian way as the geodesic distance from this area grows" (:func:`region_triangle_weights`).

Where the regions come from:

* the actor's region map (``ActorData.regions`` with the keys of
  :data:`~.params.VOLUNTARY_REGIONS`), when the user gives one;
* otherwise :func:`derive_regions` finds them in the database's motion, in the spirit of
  Tena et al.: vertices that move (RMS motion above a fraction of the 99th percentile)
  are clustered on the *correlation* of their motion over the database frames — each
  vertex's displacement trajectory (3 × frames), centred over time and scaled to unit
  length, so the dot product of two trajectories is their correlation; reduced to its
  leading singular directions and split in two by spherical k-means (seeded k-means++).
  Faces move as an upper part (brows, forehead, eyelids: raise, furrow, squint) and a
  lower part (mouth, cheeks, chin, jaw: smile, pucker, speech) that are mostly
  uncorrelated; the cluster whose vertices sit higher along ``up`` is the brow, the other
  the mouth. Each is split left/right at the mid-plane across ``left`` through the mean
  of the moving vertices, and every region keeps its largest connected piece.
  Departure: the paper uses Tena's 13-region segmentation and picks four by hand; two
  correlation clusters times two sides give the same four voluntary regions with no
  manual step, but not the involuntary ones (which the paper does not match anyway).
"""

from __future__ import annotations

import numpy as np
from scipy.sparse.csgraph import connected_components

from service.geometry.geodesic import HeatGeodesics
from service.geometry.topology import adjacency_matrix, vertex_face_adjacency
from service.methods.inputs import InvalidInput
from service.methods.shape_space.params import REGION_WEIGHT_FLOOR, VOLUNTARY_REGIONS

#: singular directions of the motion trajectories kept for the clustering
MOTION_COMPONENTS = 16
#: k-means++ restarts of the region clustering (the best inertia wins)
KMEANS_RESTARTS = 4
#: k-means iterations (at most; it stops when the labels settle)
KMEANS_ITERATIONS = 100


def region_triangle_weights(V: np.ndarray, F: np.ndarray, region_vertices: np.ndarray,
                            falloff: float, geodesics: HeatGeodesics | None = None) -> np.ndarray:
    """Soft region weights ω_r per triangle (bermano2014 §4.3, §5.3).

    ``ω_{r,t} = exp(-d̄_t² / (2 σ²))`` with d̄_t the mean geodesic distance of triangle t's
    corners from region r (0 for vertices of the region), so ω = 1 on triangles inside the
    region and decays as a Gaussian of the distance outside.

    Parameters
    ----------
    V : (n,3) float                  the neutral, mm
    F : (m,3) int
    region_vertices : (R,n) bool     vertex sets of the regions (each non-empty)
    falloff : float                  σ, mm (the paper gives no value)
    geodesics : HeatGeodesics | None  a prebuilt solver on (V, F) (built here otherwise)

    Returns
    -------
    omega : (R,m) float64 in [0, 1]

    Notes
    -----
    Distances are heat-method geodesics (:mod:`service.geometry.geodesic`) from the
    region's *rim* (its vertices with a neighbour outside), not from all its vertices: with
    a large source set the heat method's normalized gradient is meaningless inside the set
    (the heat there is nearly uniform), and the integrated distance came out offset by
    ~25 mm outside a 30 mm wide region on a test sheet; from the rim it is within a ring
    of the edge-graph distance. Vertices in components without a region vertex get weight 0.
    """
    region_vertices = np.asarray(region_vertices, dtype=bool)
    F = np.asarray(F, dtype=np.int64)
    n = len(V)
    geodesics = geodesics or HeatGeodesics(V, F)
    A = adjacency_matrix(F, n).astype(np.float64)
    out = np.empty((len(region_vertices), len(F)))
    for r, sel in enumerate(region_vertices):
        if not sel.any():
            raise ValueError(f"region {r} has no vertices")
        rim = sel & (A @ (~sel).astype(np.float64) > 0)
        if rim.any():
            d = geodesics.distance(np.flatnonzero(rim))
        else:                                         # the region covers its components
            d = np.where(sel, 0.0, np.inf)
        d[sel] = 0.0
        dt = d[F].mean(axis=1)
        with np.errstate(invalid="ignore"):
            out[r] = np.where(np.isfinite(dt), np.exp(-dt ** 2 / (2.0 * falloff ** 2)), 0.0)
    return out


def normalize_region_weights(omega: np.ndarray) -> np.ndarray:
    """``ω_{r,·} / Σ_ρ ω_{ρ,·}`` (bermano2014 eq. 4's normalization), (R,k) → (R,k).

    Columns whose sum is below :data:`~.params.REGION_WEIGHT_FLOOR` (far from every region,
    where the Gaussians underflow) get equal weights 1/R instead of 0/0.
    """
    omega = np.asarray(omega, dtype=np.float64)
    total = omega.sum(axis=0)
    low = total < REGION_WEIGHT_FLOOR
    out = omega / np.where(low, 1.0, total)
    out[:, low] = 1.0 / len(omega)
    return out


def vertex_region_weights(F: np.ndarray, omega: np.ndarray, n: int) -> np.ndarray:
    """Per-vertex region weights (R,n): the mean ω of the triangles around each vertex.

    Used to blend per-vertex colours with the matching weights (§5.5). Vertices used by no
    triangle get 0.
    """
    A = vertex_face_adjacency(np.asarray(F, dtype=np.int64), n).astype(np.float64)
    deg = np.asarray(A.sum(axis=1)).ravel()
    return (A @ np.asarray(omega, dtype=np.float64).T).T / np.where(deg > 0, deg, 1.0)


def actor_regions(regions: dict, n: int) -> np.ndarray:
    """The four voluntary regions (4,n) bool from an actor's named vertex sets.

    Raises :class:`~service.methods.inputs.InvalidInput` if a name of
    :data:`~.params.VOLUNTARY_REGIONS` is missing, has the wrong shape or is empty.
    """
    out = np.zeros((len(VOLUNTARY_REGIONS), n), dtype=bool)
    for r, name in enumerate(VOLUNTARY_REGIONS):
        if name not in regions:
            raise InvalidInput(f"the actor has no region '{name}' (needs {list(VOLUNTARY_REGIONS)})")
        sel = np.asarray(regions[name])
        if sel.shape != (n,):
            raise InvalidInput(f"region '{name}' must be ({n},) bool, got {sel.shape}")
        out[r] = sel.astype(bool)
        if not out[r].any():
            raise InvalidInput(f"region '{name}' is empty")
    return out


def _kmeans(X: np.ndarray, k: int, rng: np.random.Generator) -> tuple[np.ndarray, float]:
    """Seeded k-means (k-means++ init, Lloyd iterations): labels (a,) and inertia."""
    a = len(X)
    centres = [X[rng.integers(a)]]
    for _ in range(1, k):
        d2 = np.min(((X[:, None, :] - np.array(centres)[None]) ** 2).sum(-1), axis=1)
        centres.append(X[rng.choice(a, p=d2 / d2.sum())] if d2.sum() > 0 else X[rng.integers(a)])
    C = np.array(centres)
    labels = np.full(a, -1)
    for _ in range(KMEANS_ITERATIONS):
        d2 = ((X[:, None, :] - C[None]) ** 2).sum(-1)
        new = np.argmin(d2, axis=1)
        if np.array_equal(new, labels):
            break
        labels = new
        for c in range(k):
            if np.any(labels == c):
                C[c] = X[labels == c].mean(axis=0)
    inertia = float(((X - C[labels]) ** 2).sum())
    return labels, inertia


def _largest_piece(F: np.ndarray, n: int, sel: np.ndarray) -> np.ndarray:
    """The largest connected piece (n,) bool of a vertex set under the mesh adjacency."""
    idx = np.flatnonzero(sel)
    if len(idx) == 0:
        return sel
    A = adjacency_matrix(F, n)[idx][:, idx]
    _, lab = connected_components(A, directed=False)
    out = np.zeros(n, dtype=bool)
    out[idx[lab == np.argmax(np.bincount(lab))]] = True
    return out


def derive_regions(neutral: np.ndarray, F: np.ndarray, displacements: np.ndarray,
                   up: np.ndarray, left: np.ndarray, motion_fraction: float = 0.2,
                   seed: int = 0) -> tuple[np.ndarray, dict]:
    """Four voluntary regions from the database's motion correlation (bermano2014 §4.3).

    See the module docstring for the procedure and how it departs from the paper.

    Parameters
    ----------
    neutral : (n,3) float          d0, mm
    F : (m,3) int
    displacements : (N,n,3) float  aligned database frames minus the neutral, mm
    up, left : (3,) float          the actor's up and left directions
    motion_fraction : float        moving vertices: RMS motion > this × 99th percentile
    seed : int                     k-means seed

    Returns
    -------
    regions : (4,n) bool   in the order of :data:`~.params.VOLUNTARY_REGIONS`
    info : dict            ``moving`` (count), ``threshold_mm``, ``cluster_sizes``

    Raises
    ------
    InvalidInput   the database does not move enough to find two groups on both sides
    """
    neutral = np.asarray(neutral, dtype=np.float64)
    F = np.asarray(F, dtype=np.int64)
    U = np.asarray(displacements, dtype=np.float64)
    N, n = U.shape[:2]
    up = np.asarray(up, dtype=np.float64) / np.linalg.norm(up)
    left = np.asarray(left, dtype=np.float64) / np.linalg.norm(left)
    rms = np.sqrt(np.einsum("fnd,fnd->n", U, U) / max(N, 1))
    threshold = motion_fraction * float(np.percentile(rms, 99))
    moving = rms > threshold
    if N < 2 or moving.sum() < 8 or threshold <= 0:
        raise InvalidInput("the database does not move enough to derive regions "
                           f"({int(moving.sum())} moving vertices over {N} frames); give the "
                           f"actor's regions {list(VOLUNTARY_REGIONS)} or use regions='whole'")
    Um = U[:, moving, :]
    traj = (Um - Um.mean(axis=0)).transpose(1, 0, 2).reshape(-1, 3 * N)   # centred over time
    traj /= np.maximum(np.linalg.norm(traj, axis=1, keepdims=True), 1e-12)
    _, s, Vt = np.linalg.svd(traj, full_matrices=False)
    r = min(MOTION_COMPONENTS, len(s))
    X = traj @ Vt[:r].T
    X /= np.maximum(np.linalg.norm(X, axis=1, keepdims=True), 1e-12)      # spherical k-means
    rng = np.random.default_rng(seed)
    best = min((_kmeans(X, 2, rng) for _ in range(KMEANS_RESTARTS)), key=lambda t: t[1])
    labels = best[0]
    P = neutral[moving]
    height = np.array([(P[labels == c] @ up).mean() if np.any(labels == c) else -np.inf for c in (0, 1)])
    brow = np.zeros(n, dtype=bool)
    brow[np.flatnonzero(moving)[labels == int(np.argmax(height))]] = True
    mouth = moving & ~brow
    side = (neutral - P.mean(axis=0)) @ left > 0
    regions = np.stack([mouth & side, mouth & ~side, brow & side, brow & ~side])
    regions = np.stack([_largest_piece(F, n, sel) for sel in regions])
    empty = [VOLUNTARY_REGIONS[r] for r in range(4) if not regions[r].any()]
    if empty:
        raise InvalidInput(f"could not derive the regions {empty} from the database motion; "
                           f"give the actor's regions or use regions='whole'")
    info = {"moving": int(moving.sum()), "threshold_mm": threshold,
            "cluster_sizes": [int(x) for x in regions.sum(axis=1)]}
    return regions, info
