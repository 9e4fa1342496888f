"""The fully coupled tracking energy and its minimization (fyffe, digital_ira_course2014, §5).

Unknowns: the artist mesh's vertex positions x_i^p of every pose p in a common head frame
and a rigid head-to-world transform (R_p, t_p) per pose. Energy (eq. 1)::

    E = Σ_(p,q)∈F (E_corr^pq + E_corr^qp) + Σ_p |F_p| β E_shape^p + Σ_p∈S |F_p| γ E_wrap^p + E_ground

* :func:`correspondence_model` — eq. 2–4: the flowed projection of x_i^p defines a view ray
  that x_i^q should lie on; the quadratic (x^q − x^p − f)ᵀ F (x^q − x^p − f) with
  f = (I − r rᵀ)(o − x^p) and F = c · v · conf · (I − r rᵀ + ε I);
* :func:`shape_targets` — eq. 5–7: every mesh edge of pose p pulled to the blend of its graph
  neighbours' and the artist mesh's edge vectors, weighted by the correspondence strengths;
* :func:`wrap_model` — eq. 8–11: point-to-plane distance of a static pose to its raw scan
  (nearest scan point by KD-tree, its normal), weighted by exp(−‖d − y‖²/σ²) and visibility;
* the ground term (eq. 12): the neutral pose is held at the artist mesh (the term's weight
  taken to infinity: the neutral *is* the artist's mesh and its transform the user's);
* :func:`update_rigid` — §5.6: weighted SVD alignment of the artist mesh to each pose.

Departure from the paper's minimizer (§5.1, lazy DDMS-TRW-S). :func:`solve_poses` keeps the
outer loop of DDMS — each iteration re-fits every term as a quadratic model at the current
estimate (correspondence rays, shape targets, shrink-wrap planes, visibility) — but
minimizes the sum of the quadratics over *all free poses of the call at once*, as one
sparse linear least-squares system, instead of by Gaussian message passing. The system's
matrix is the per-vertex 3×3 blocks of the data terms (diagonal and between the two poses
of an edge, one BSR matrix) plus β_p · (DᵀD ⊗ I₃) per pose (D the mesh's edge-incidence
matrix, applied as one sparse product over all poses), assembled in :class:`PoseSystem` and
solved by conjugate gradients with a 3×3 block-Jacobi preconditioner, warm-started at the
current estimate.
(A direct factorization, :mod:`service.geometry.sparse_solve`, took 1.6 s for one pose of
the 11k-vertex mesh and 195 s for five coupled poses — the pose coupling fills in like a
3-D grid; CG takes ~0.1 s per pose.) TRW-S's lazy model construction — terms are fitted
only once the belief of their source is defined, so information spreads outward from the
ground — is kept as a per-vertex *certainty* c_i^p ∈ [0, 1] (the scalar precision
min(1, det(Σ⁻¹)^⅓) of eq. 4 and 11): the ground pose has 1, every other pose starts at 0
and gains min(1, gain · Σ_incoming conf · v · c_source) after each solve; a correspondence
is weighted by its *source's* certainty, a shape neighbour by its own.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
import scipy.sparse as sp
from scipy.spatial import cKDTree

from service.geometry import optical_flow as of
from service.geometry.camera import Camera, rasterize
from service.geometry.normals import vertex_normals
from service.geometry.rigid import rigid_align
from service.geometry.topology import adjacency_matrix, edges
from service.methods.tracking.graph import EdgeFlows
from service.methods.tracking.params import TrackingParams


@dataclass
class PoseState:
    """One pose: X (n,3) head-frame positions (mm), R (3,3), t (3,) head → world,
    certainty (n,) in [0, 1]."""

    X: np.ndarray
    R: np.ndarray
    t: np.ndarray
    certainty: np.ndarray

    def world(self) -> np.ndarray:
        """World positions (n,3): ``R x + t``."""
        return self.X @ self.R.T + self.t


@dataclass
class TrackingMesh:
    """The artist mesh and what the terms need of it, built once.

    Attributes
    ----------
    artist : (n,3) float   the neutral (ground) pose, head frame = world of the neutral
    faces : (m,3) int;  E : (e,2) int mesh edges;  D : (e,n) sparse edge incidence (x_j − x_i)
    smooth : (n,n) sparse  one-ring averaging (the soft visibility's blur)
    rigidity : (n,) float  rigidity weights of §5.6 (default 1; set from the static poses)
    size_weights : (n,) float or None   the size region of monocular depth
                           (:func:`size_region`; None until estimated from static poses)
    size_band : float      the relative scale the static poses themselves show over the size
                           region (:func:`size_band`; 0 until estimated): monocular scale
                           evidence within it moves nothing
    """

    artist: np.ndarray
    faces: np.ndarray
    E: np.ndarray
    D: sp.csr_matrix
    smooth: sp.csr_matrix
    rigidity: np.ndarray
    size_weights: np.ndarray | None = None
    size_band: float = 0.0

    @classmethod
    def build(cls, artist: np.ndarray, faces: np.ndarray) -> "TrackingMesh":
        V = np.asarray(artist, np.float64)
        F = np.asarray(faces, np.int64)
        n = len(V)
        E, _ = edges(F)
        m = len(E)
        D = sp.csr_matrix((np.r_[np.ones(m), -np.ones(m)],
                           (np.r_[np.arange(m), np.arange(m)], np.r_[E[:, 1], E[:, 0]])), shape=(m, n))
        A = adjacency_matrix(F, n) + sp.eye(n)
        smooth = sp.diags(1.0 / np.asarray(A.sum(axis=1)).ravel()) @ A
        return cls(V, F, E, D.tocsr(), sp.csr_matrix(smooth), np.ones(n))

    @property
    def n(self) -> int:
        return len(self.artist)


@dataclass
class RawScan:
    """A static pose's raw scan geometry (world, mm): points (k,3), unit normals (k,3)."""

    points: np.ndarray
    normals: np.ndarray
    tree: cKDTree

    @classmethod
    def build(cls, points: np.ndarray, faces: np.ndarray) -> "RawScan":
        P = np.asarray(points, np.float64)
        return cls(P, vertex_normals(P, np.asarray(faces, np.int64), weighting="area"), cKDTree(P))


def visibility(mesh: TrackingMesh, camera: Camera, world: np.ndarray, tolerance_mm: float,
               max_size: int | None = None) -> np.ndarray:
    """Soft visibility (n,) in [0, 1] of the vertices in one view (eq. 4's v_p^c).

    Binary visibility by z-buffer (the vertex's depth within ``tolerance_mm`` of the
    rasterized depth at its pixel), blurred over the one-ring twice, times the cosine between
    the vertex normal and the direction to the camera (clipped at 0). ``max_size``: the
    z-buffer is rasterized with the camera scaled so its longest side is at most this many
    pixels (None: the camera's own size); the depth test only needs the surface's depth
    near each vertex, not the image's resolution.
    """
    if max_size is not None and max(camera.width, camera.height) > max_size:
        camera = camera.scaled(max_size / max(camera.width, camera.height))
    triangle, bary = rasterize(camera, world, mesh.faces)
    p = camera.project(world)
    H, W = triangle.shape
    col = np.floor(p[:, 0]).astype(np.int64)
    row = np.floor(p[:, 1]).astype(np.int64)
    inside = (col >= 0) & (col < W) & (row >= 0) & (row < H) & (p[:, 2] > 0)
    vis = np.zeros(len(world))
    idx = np.flatnonzero(inside)
    tri = triangle[row[idx], col[idx]]
    hit = tri >= 0
    idx, tri = idx[hit], tri[hit]
    zbuf = np.einsum("pk,pk->p", bary[row[idx], col[idx]], p[mesh.faces[tri], 2])
    vis[idx] = (np.abs(zbuf - p[idx, 2]) <= tolerance_mm).astype(np.float64)
    vis = mesh.smooth @ (mesh.smooth @ vis)
    N = vertex_normals(world, mesh.faces, weighting="area")
    to_cam = camera.centre - world
    to_cam /= np.linalg.norm(to_cam, axis=1, keepdims=True)
    return vis * np.clip(np.einsum("nd,nd->n", N, to_cam), 0.0, 1.0)


@dataclass
class CorrespondenceModel:
    """The quadratic (x^q − x^p − f)ᵀ F (x^q − x^p − f) of one direction of one edge in one
    view (eq. 2–4): f (n,3), F (n,3,3); ``strength`` (n,) = v · conf (without certainty)."""

    f: np.ndarray
    F: np.ndarray
    strength: np.ndarray
    weight: np.ndarray


def correspondence_model(source: PoseState, target: PoseState, camera: Camera, vis: np.ndarray,
                         flow: np.ndarray, confidence: np.ndarray, epsilon: float) -> CorrespondenceModel:
    """Fit eq. 2–4 for the flow source → target in one view.

    Project ỹ^p = R_p x^p + t_p into the view (pixel centres: the camera's integer + 0.5 are
    the flow images' integers), move the point by the flow, and cast the view ray through
    it; in the target's head frame it has origin o = R_qᵀ(c − t_q) and direction r = R_qᵀ d,
    so f = (I − r rᵀ)(o − x^p) (eq. 3) and F = c_p · v · conf · (I − r rᵀ + ε I) (eq. 4).

    Parameters
    ----------
    source, target : the two poses' current states
    camera : the view;  vis : (n,) soft visibility of the source in it
    flow : (H,W,2) backward flow on the source image (target(x + flow) ≈ source(x))
    confidence : (H,W) its NCC confidence;  epsilon : ε of eq. 4
    """
    H, W = confidence.shape
    p = camera.project(source.world())
    xy = p[:, :2] - 0.5
    moved = xy + of.sample(flow, xy)
    conf = of.sample(confidence, xy, border=0.0).astype(np.float64)
    inside = ((xy >= 0) & (xy <= [W - 1, H - 1])).all(axis=1) & \
             ((moved >= 0) & (moved <= [W - 1, H - 1])).all(axis=1)
    strength = np.where(inside, vis * np.clip(conf, 0.0, 1.0), 0.0)
    d = camera.rays(moved + 0.5)                              # world directions
    r = d @ target.R                                          # R_qᵀ d, row-wise
    o = (camera.centre - target.t) @ target.R                 # R_qᵀ (c − t_q)
    P = np.eye(3)[None] - r[:, :, None] * r[:, None, :]
    f = np.einsum("nij,nj->ni", P, o[None, :] - source.X)
    weight = source.certainty * strength
    F = weight[:, None, None] * (P + epsilon * np.eye(3)[None])
    return CorrespondenceModel(f, F, strength, weight)


def shape_targets(mesh: TrackingMesh, neighbours: list[tuple[np.ndarray, np.ndarray]],
                  artist_weight: float) -> np.ndarray:
    """Blended target edge vectors I_ij (e,3) of one pose (eq. 6–7).

    Parameters
    ----------
    neighbours : list of (X_q (n,3) head-frame positions of a graph neighbour q,
                 w_q (n,) its per-vertex strength w_i^pq)
    artist_weight : λ of eq. 6 (the artist mesh g's share)
    """
    i, j = mesh.E[:, 0], mesh.E[:, 1]
    num = artist_weight * (mesh.artist[j] - mesh.artist[i])
    den = np.full(len(i), artist_weight)
    for Xq, wq in neighbours:
        wi, wj = wq[i], wq[j]
        with np.errstate(invalid="ignore", divide="ignore"):
            wij = np.where(wi + wj > 0, wi * wj / (wi + wj), 0.0)          # eq. 7
        num += wij[:, None] * (Xq[j] - Xq[i])
        den += wij
    return num / den[:, None]


def wrap_model(state: PoseState, scan: RawScan, vis: np.ndarray, sigma_mm: float,
               epsilon: float) -> tuple[np.ndarray, np.ndarray]:
    """Fit eq. 8–11: the plane (n_i, d_i) of the raw scan nearest each vertex, head frame.

    The paper samples the scan through rasterized views; here the nearest scan point by
    KD-tree (its area-weighted normal), weighted by ω = v · exp(−‖d̂ − ỹ‖²/σ²) (eq. 11's
    sample weight) and the pose's certainty.

    Returns
    -------
    d : (n,3) plane points (head frame);  G : (n,3,3) = g (n nᵀ + ε I)
    """
    y = state.world()
    dist, idx = scan.tree.query(y, k=1)
    n_world = scan.normals[idx]
    g = state.certainty * vis * np.exp(-(dist / sigma_mm) ** 2)
    n = n_world @ state.R
    d = (scan.points[idx] - state.t) @ state.R
    G = g[:, None, None] * (n[:, :, None] * n[:, None, :] + epsilon * np.eye(3)[None])
    return d, G


class PoseSystem:
    """The sparse normal equations of one outer iteration over P free poses.

    Unknown vector: the free poses' head-frame positions, (P,n,3) flattened. The matrix is
    ``blockdiag_p(B_p) + Σ_pairs (C_pq, C_qp) + ⊕_p β_p (DᵀD ⊗ I₃)``: per-vertex 3×3
    diagonal blocks B (P,n,3,3), per-vertex 3×3 coupling blocks between two free poses,
    and each pose's scalar Laplacian weight.
    """

    def __init__(self, mesh: TrackingMesh, P: int):
        self.mesh, self.P, self.n = mesh, P, mesh.n
        self.B = np.zeros((P, self.n, 3, 3))
        self.b = np.zeros((P, self.n, 3))
        self.coupling: dict[tuple[int, int], np.ndarray] = {}
        self.beta = np.zeros(P)
        self.L = (mesh.D.T @ mesh.D).tocsr()

    def add_pair(self, a: int | None, b: int | None, F: np.ndarray, m: np.ndarray,
                 xa: np.ndarray | None = None, xb: np.ndarray | None = None) -> None:
        """Add (x_b − x_a − m)ᵀ F (x_b − x_a − m); a or b None when that pose is fixed at xa/xb."""
        Fm = np.einsum("nij,nj->ni", F, m)
        if a is not None and b is not None:
            self.B[a] += F
            self.B[b] += F
            self.b[b] += Fm
            self.b[a] -= Fm
            key = (a, b) if a < b else (b, a)
            self.coupling[key] = self.coupling.get(key, 0.0) - F
        elif b is not None:                      # x_a fixed: (x_b − (x_a + m))
            self.B[b] += F
            self.b[b] += np.einsum("nij,nj->ni", F, xa + m)
        elif a is not None:                      # x_b fixed: (x_a − (x_b − m))
            self.B[a] += F
            self.b[a] += np.einsum("nij,nj->ni", F, xb - m)

    def add_point(self, a: int, G: np.ndarray, d: np.ndarray) -> None:
        """Add (x_a − d)ᵀ G (x_a − d)."""
        self.B[a] += G
        self.b[a] += np.einsum("nij,nj->ni", G, d)

    def add_shape(self, a: int, beta: float, targets: np.ndarray) -> None:
        """Add β ‖D x_a − I‖² (eq. 5)."""
        self.beta[a] += beta
        self.b[a] += beta * (self.mesh.D.T @ targets)

    def block_matrix(self, vertex_major: bool = False) -> sp.bsr_matrix:
        """The data terms' 3×3 blocks as one (3Pn, 3Pn) BSR matrix: B on the diagonal, each
        coupling block at (a, b) and (b, a) (the blocks are symmetric). Unknowns ordered
        pose-major (p, i, ·) or, with ``vertex_major``, (i, p, ·)."""
        P, n = self.P, self.n
        idx = np.arange(n)

        def unknown(p):
            return idx * P + p if vertex_major else p * n + idx

        rows = [unknown(p) for p in range(P)]
        cols = [unknown(p) for p in range(P)]
        data = [self.B[p] for p in range(P)]
        for (a, b), C in self.coupling.items():
            rows += [unknown(a), unknown(b)]
            cols += [unknown(b), unknown(a)]
            data += [C, C]
        r, c = np.concatenate(rows), np.concatenate(cols)
        order = np.lexsort((c, r))
        indptr = np.searchsorted(r[order], np.arange(P * n + 1))
        return sp.bsr_matrix((np.concatenate(data)[order], c[order], indptr),
                             shape=(3 * P * n, 3 * P * n), blocksize=(3, 3))

    def matvec(self, x: np.ndarray) -> np.ndarray:
        """The system matrix times x (3Pn,), pose-major (the reference product; the CG loop
        applies the same matrix vertex-major, :meth:`solve`)."""
        X = x.reshape(self.P, self.n, 3)
        Y = (self.block_matrix() @ x).reshape(self.P, self.n, 3)
        for p in np.flatnonzero(self.beta):
            Y[p] += self.beta[p] * (self.L @ X[p])
        return Y.ravel()

    def solve(self, x0: np.ndarray, iterations: int, rtol: float = 1e-6) -> np.ndarray:
        """Conjugate gradients, 3×3 block-Jacobi preconditioned, from x0 (P,n,3).

        Written out rather than ``scipy.sparse.linalg.cg``: its BLAS dot products on
        vectors of this size spent 20 of 35 s in OpenBLAS thread start-up on a loaded
        2-core machine; elementwise products summed by NumPy do not thread. The unknowns
        are ordered vertex-major inside the loop, so the data blocks and the
        preconditioner are one BSR matrix each and β_p (DᵀD ⊗ I₃) is one sparse product
        ``L @ X`` with X (n, 3P): 2.4× less CPU per product than the per-pose einsum and
        Laplacian products (8 poses of the 11k-vertex mesh).
        """
        P, n = self.P, self.n
        diagL = self.L.diagonal()
        M = self.B + (self.beta[:, None] * diagL[None, :])[..., None, None] * np.eye(3)
        Minv = np.ascontiguousarray(np.linalg.inv(M).transpose(1, 0, 2, 3)).reshape(n * P, 3, 3)
        precond = sp.bsr_matrix((Minv, np.arange(n * P), np.arange(n * P + 1)),
                                shape=(3 * P * n, 3 * P * n), blocksize=(3, 3))
        block = self.block_matrix(vertex_major=True)
        weights = np.repeat(self.beta, 3)[None, :]                     # (1, 3P)
        lap = bool(np.any(self.beta))

        def apply(v):
            out = block @ v
            if lap:
                out += ((self.L @ v.reshape(n, 3 * P)) * weights).ravel()
            return out

        def dot(a, b):
            return float(np.einsum("i,i->", a, b))

        b = np.ascontiguousarray(self.b.transpose(1, 0, 2)).ravel()
        x = np.ascontiguousarray(np.asarray(x0, np.float64).reshape(P, n, 3).transpose(1, 0, 2)).ravel()
        r = b - apply(x)
        z = precond @ r
        p = z.copy()
        rz = dot(r, z)
        stop = rtol * np.sqrt(dot(b, b))
        for _ in range(iterations):
            if np.sqrt(dot(r, r)) <= stop:
                break
            Ap = apply(p)
            alpha = rz / dot(p, Ap)
            x += alpha * p
            r -= alpha * Ap
            z = precond @ r
            rz_new = dot(r, z)
            p = z + (rz_new / rz) * p
            rz = rz_new
        return np.ascontiguousarray(x.reshape(n, P, 3).transpose(1, 0, 2))


def update_rigid(mesh: TrackingMesh, state: PoseState, centre: np.ndarray | None = None,
                 size_weights: np.ndarray | None = None, tolerance: float = 0.0) -> PoseState:
    """§5.6: re-estimate (R_p, t_p) by aligning the artist mesh to the current result.

    Weighted SVD (:func:`~service.geometry.rigid.rigid_align`) of g onto ỹ = R x + t with
    the rigidity weights times the certainty; the world positions do not change, the head
    frame positions become x = R′ᵀ(ỹ − t′).

    ``centre`` (3,): the nodal point of the *only* camera (monocular input). Then the head's
    distance along the view rays is taken from its size: ỹ is first scaled about the
    camera centre, ỹ′ = c + s (ỹ − c), with s the weighted least-squares (Umeyama 1991)
    scale that takes ỹ onto the artist mesh g, weighted by ``size_weights`` (n,) times the
    certainty: the vertices the static poses deform least (:func:`size_region`). The
    scaling moves every vertex along its own view ray, so no projection into that view
    changes, and the skull-fixed part of the face gets the artist mesh's size.

    Departure from the paper (measured, family b, 256², 40 frames, 1 view): §5.6's rigid
    fit keeps the world positions, and in one view nothing but ε of eq. 4 reaches the
    depth. That term pulls x^q to the point of the flowed ray nearest x^p in the head
    frame, so every pose keeps the neutral's distance, and a head 4–8 mm nearer or farther
    is explained by a face scaled up to 1 % (frame 0: centroid 5.3 mm behind the truth,
    scale 1.0097). The size has to come from skin that expressions do not stretch: the
    ground-truth frames' own scale against the artist mesh spans 0.987–1.012 over the face
    (5 mm of depth at 520 mm) and 0.993–1.010 with the rigidity weights, but 0.998–1.002
    over the tenth of the face the static scans deform least.

    ``tolerance``: the scale evidence is soft-thresholded, s ← 1 + sign(s − 1)·max(|s − 1|
    − tol, 0) (the proximal step of an L1 prior on the head's depth change): within the
    size measure's noise the neutral's distance is kept. Measured (256², 40 frames, 1 view,
    mean face error, mm; a's head barely moves in depth, b's by ±8 mm):

    ==========  =====  =====  =====  =====  =====
    family      off    0      0.002  0.004  0.006
    ==========  =====  =====  =====  =====  =====
    a           0.700  1.356  0.970  0.759  0.700
    b           3.177  1.799         1.653  1.837
    ==========  =====  =====  =====  =====  =====

    Chosen on a (the smallest tolerance that costs a nothing: 0.006), confirmed on b
    (3.18 → 1.84 mm; the head's depth offset at most 3.9 mm instead of 6.9). These rows
    took the size region as the tenth of the face with the highest rigidity weights (a:
    0.05 / 0.1 / 0.2 of it gave 1.60 / 1.36 / 1.24 mm at tolerance 0, all worse than off, so
    a cannot choose the fraction; 0.1 is the truth frames' best in the measurement above).
    Final (:func:`size_region` from the largest residual, the tolerance raised to
    :func:`size_band` where the scans' own expressions change the region's size), mean face
    error, mm, 256², 1 view, load 2–4.5:

    ==========  ==========  =========  ===========  ==========
    family      40 fr off   40 fr on   120 fr off   120 fr on
    ==========  ==========  =========  ===========  ==========
    a           0.700       0.717      1.273        1.503
    b           3.177       1.803      2.480        2.291
    ==========  ==========  =========  ===========  ==========

    So it is off by default (``TrackingParams.monocular_depth``): on a's 120 frames,
    frames 36–66 are an expression the scans do not show that changes the size region's
    scale by ~0.5 %, and the update moves them 2–4 mm along the axis (depth error 4.35 mm at
    frame 42 against ≤ 0.35 mm before frame 36). The size evidence needs the frame's
    expected size, not the neutral's: see the note in the session's report.
    """
    w = mesh.rigidity * state.certainty
    if np.count_nonzero(w > 1e-6) < 10:
        return state
    y = state.world()
    if centre is not None and size_weights is not None:
        ws = size_weights * state.certainty
        if np.count_nonzero(ws > 1e-6) >= 10:
            s = rigid_align(y, mesh.artist, weights=ws, scale=True).s
            s = 1.0 + np.sign(s - 1.0) * max(abs(s - 1.0) - tolerance, 0.0)
            y = centre + s * (y - centre)
    T = rigid_align(mesh.artist, y, weights=w)
    return replace(state, X=(y - T.t) @ T.R, R=T.R, t=T.t)


def size_region(mesh: TrackingMesh, poses: list[np.ndarray], fraction: float,
                face: np.ndarray | None = None) -> np.ndarray | None:
    """(n,) 0/1 weights of the part of the face that no static pose deforms: the
    ``fraction`` of the face vertices with the smallest *largest* residual over the static
    poses (each head-frame pose rigidly aligned onto the artist mesh with the rigidity
    weights, §5.6); None without poses.

    The largest residual, not the RMS of the rigidity weights: a vertex one scanned
    expression moves is not rigid (family b, 40 frames: the tenth with the highest
    rigidity weights had one scan's size 1.4 % off the artist mesh's, the truth 2.6 %).
    """
    if not poses:
        return None
    res = np.zeros(mesh.n)
    for X in poses:
        T = rigid_align(X, mesh.artist, weights=np.maximum(mesh.rigidity, 1e-9))
        res = np.maximum(res, np.linalg.norm(T.apply(X) - mesh.artist, axis=1))
    cand = np.ones(mesh.n, bool) if face is None else np.asarray(face, bool)
    return (cand & (res <= np.quantile(res[cand], fraction))).astype(np.float64)


def size_band(mesh: TrackingMesh, poses: list[np.ndarray], region: np.ndarray | None) -> float:
    """The median |s − 1| of the static poses' own scale against the artist mesh over the
    size region (:func:`size_region`): how much the expressions the scans show change the
    size that monocular depth is read from (0 without poses or a size region).

    The static poses' depth is known (shrink-wrap, eq. 8), so this scale is expression, not
    distance. A monocular scale estimate within max(tolerance, band) of 1 is ignored
    (:func:`update_rigid`). The median over the poses, not the largest: one scanned
    expression of five that changes the region's size (b's first scan: 1.4 %, the truth
    2.6 %) would otherwise switch the cue off for the whole performance (band 0.0113, b's
    monocular error 2.97 mm instead of 1.80). Measured: the tracking scene of the job tests
    (a 60 mm cap with an 8 mm bump over most of it: no rigid part) 0.021 — without the band
    its 1-view error rose from 0.98 to 3.68 mm, with it 0.996; family a 0.0023, b 0.0036
    (below the tolerance: no effect).
    """
    if region is None or not poses:
        return 0.0
    return float(np.median([abs(rigid_align(X, mesh.artist, weights=region, scale=True).s - 1.0)
                            for X in poses]))


def solve_poses(mesh: TrackingMesh, cameras: list[Camera], states: dict, free: list,
                edges_: list[EdgeFlows], scans: dict, params: TrackingParams, iterations: int,
                rigid: bool = True) -> dict:
    """Minimize eq. 1 over the ``free`` poses with the others fixed (one solver call).

    Parameters
    ----------
    mesh : the artist mesh;  cameras : C views (the flows' images are theirs)
    states : pose key → PoseState for every pose the edges touch (free ones are the start)
    free : keys of the poses solved for (the rest of ``states`` is held fixed)
    edges_ : the graph edges among these poses, with flows per view
    scans : pose key → RawScan for the static poses with a shrink-wrap term
    iterations : outer (model re-fitting) iterations

    Returns
    -------
    states : the input mapping with the free poses replaced by their solution
    """
    states = dict(states)
    index = {k: i for i, k in enumerate(free)}
    degree = {k: 0 for k in states}
    for e in edges_:
        degree[e.source] += 1
        degree[e.target] += 1
    views = len(cameras)
    centre, size = None, None
    if views == 1 and params.monocular_depth:
        centre, size = cameras[0].centre, mesh.size_weights
    fixed_vis = {}
    for it in range(iterations):
        vis = {}
        for k in {e.source for e in edges_} | {e.target for e in edges_} | set(scans):
            if k in index or k not in fixed_vis:
                vis[k] = [visibility(mesh, c, states[k].world(), params.visibility_tolerance_mm,
                                      params.visibility_size)
                          for c in cameras]
                if k not in index:
                    fixed_vis[k] = vis[k]
            else:
                vis[k] = fixed_vis[k]
        system = PoseSystem(mesh, len(free))
        strength: dict[tuple, np.ndarray] = {}
        incoming = {k: np.zeros(mesh.n) for k in free}
        for e in edges_:
            for src, dst, flows in ((e.source, e.target, e.forward), (e.target, e.source, e.backward)):
                if src not in index and dst not in index:
                    continue
                for c, vf in enumerate(flows):
                    model = correspondence_model(states[src], states[dst], cameras[c], vis[src][c],
                                                 vf.flow, vf.confidence, params.ray_regularization)
                    system.add_pair(index.get(src), index.get(dst), model.F / views, model.f,
                                    states[src].X, states[dst].X)
                    for key in ((src, dst), (dst, src)):
                        strength[key] = strength.get(key, 0.0) + model.strength / (2 * views)
                    if dst in incoming:
                        incoming[dst] += model.weight / views
        for k, a in index.items():
            nb = [(states[q].X, strength[(k, q)] * states[q].certainty)
                  for (p, q) in strength if p == k]
            if params.shape_weight > 0:
                system.add_shape(a, params.shape_weight * max(degree[k], 1),
                                 shape_targets(mesh, nb, params.artist_shape_weight))
            if k in scans and params.wrap_weight > 0:
                d, G = wrap_model(states[k], scans[k], vis[k][0], params.wrap_sigma_mm,
                                  params.wrap_regularization)
                system.add_point(a, params.wrap_weight * max(degree[k], 1) * G, d)
            system.B[a] += params.inertia * np.eye(3)
            system.b[a] += params.inertia * states[k].X
        X0 = np.stack([states[k].X for k in free])
        X = system.solve(X0, params.cg_iterations)
        for k, a in index.items():
            s = states[k]
            certainty = np.maximum(s.certainty, np.minimum(1.0, params.certainty_gain * incoming[k]))
            new = replace(s, X=X[a], certainty=certainty)
            states[k] = update_rigid(mesh, new, None if k in scans else centre, size,
                                     max(params.monocular_scale_tolerance, mesh.size_band)) \
                if rigid else new
    return states
