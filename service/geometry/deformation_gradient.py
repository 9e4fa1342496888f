"""Triangle deformation gradients, their polar/log encoding, and Poisson reconstruction.

Forward (Sumner & Popović 2004, "Deformation transfer for triangle meshes", §3 eq. 1-4):
each triangle gets a fourth vertex along its normal scaled by ``1/sqrt(|e1 × e2|)``, and the
3×3 deformation gradient is ``G = Ṽ1 Ṽ0⁻¹`` with ``Ṽ = [v2-v1, v3-v1, v4-v1]``.

Encoding (bermano2014 §4.2 "Encoding", §5.4): ``G = R S`` (polar decomposition), the rotation
stored as its axis-angle log (3 numbers) and the symmetric stretch S (6 numbers), so
gradients are blended linearly in (log R, S) and turned back with :func:`rotation_exp`.

Inverse (bermano2014 §5.5 "Reconstruction", after Botsch et al. 2006): positions whose
per-triangle gradients best match target gradients in the area-weighted least-squares sense,
``min_x Σ_t A_t ‖∇x_t - T_t‖²``, prefactored once per rest mesh (:class:`PoissonReconstruction`).
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import connected_components

from service.geometry.sparse_solve import factorize
from service.geometry.topology import adjacency_matrix, edge_face_counts

#: Weight of the boundary 1D-Laplacian term of bermano2014 §5.5 ("a minimal weight factor of
#: w = 0.05 was sufficient to completely eliminate the artifacts").
BOUNDARY_WEIGHT = 0.05


# --------------------------------------------------------------------------- forward

def _frames(V: np.ndarray, F: np.ndarray) -> np.ndarray:
    """Sumner-Popović edge frames (..., m, 3, 3): columns ``v2-v1, v3-v1, n/sqrt(|n|)``.

    ``n = (v2-v1) × (v3-v1)``, so the third column is the unit normal scaled by
    ``1/sqrt(2 area)`` (the fourth vertex of Sumner & Popović 2004 eq. 1, minus v1).
    """
    P = V[..., F, :]                                            # (...,m,3,3) corners
    e1 = P[..., 1, :] - P[..., 0, :]
    e2 = P[..., 2, :] - P[..., 0, :]
    n = np.cross(e1, e2)
    e3 = n / np.sqrt(np.linalg.norm(n, axis=-1, keepdims=True))
    return np.stack([e1, e2, e3], axis=-1)


def rest_frames_inverse(V0: np.ndarray, F: np.ndarray) -> np.ndarray:
    """Inverse edge frames (m,3,3) ``Ṽ0_t⁻¹`` of a rest mesh, for :func:`deformation_gradients`
    of many frames against one rest mesh."""
    return inverse3(_frames(np.asarray(V0, dtype=np.float64), np.asarray(F, dtype=np.int64)))


def inverse3(X: np.ndarray) -> np.ndarray:
    """Inverses (...,3,3) of 3×3 matrices in closed form, ``X⁻¹ = cof(X)ᵀ / det X`` (several
    times faster than batched LAPACK for 3×3; singular matrices give inf/nan)."""
    X = np.asarray(X, dtype=np.float64)
    E = X.reshape(-1, 9).T
    cof = _cofactors(E)
    det = E[0] * cof[0] + E[1] * cof[1] + E[2] * cof[2]
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = (cof / det).T.reshape(-1, 3, 3)
    return np.swapaxes(inv, -1, -2).reshape(X.shape)


def deformation_gradients(V0: np.ndarray, V1: np.ndarray, F: np.ndarray,
                          rest_inverse: np.ndarray | None = None) -> np.ndarray:
    """Per-triangle deformation gradients from a rest mesh to deformed mesh(es).

    Sumner & Popović 2004 §3, eq. 1-4: ``G_t = Ṽ1_t Ṽ0_t⁻¹`` with the edge frames
    ``Ṽ = [v2-v1, v3-v1, v4-v1]`` and ``v4 = v1 + (e1 × e2) / sqrt(|e1 × e2|)``.

    Parameters
    ----------
    V0 : (n,3) float           rest vertices (mm)
    V1 : (n,3) or (B,n,3) float  deformed vertices, one mesh or a batch of B frames
    F : (m,3) int              triangles (non-degenerate in V0)
    rest_inverse : (m,3,3) float | None   :func:`rest_frames_inverse` of (V0, F), if at hand

    Returns
    -------
    G : (m,3,3) or (B,m,3,3) float64   ``G_t @ (p - v1) + v1'`` maps the rest triangle (and
        its normal direction) onto the deformed one
    """
    F = np.asarray(F, dtype=np.int64)
    if rest_inverse is None:
        rest_inverse = rest_frames_inverse(V0, F)
    return _frames(np.asarray(V1, dtype=np.float64), F) @ rest_inverse


# --------------------------------------------------------------------------- encoding

def polar_decomposition(G: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Polar decomposition ``G = R S`` with R a proper rotation and S symmetric.

    For ``det G > 0`` (every non-inverted deformation gradient) by Higham's scaled Newton
    iteration ``X ← ½(ζX + ζ⁻¹X⁻ᵀ)``, ``ζ = |det X|^(-1/3)`` (Higham 1986, "Computing the polar
    decomposition — with applications", §3), with the 3×3 inverse in closed form (cofactors),
    which converges quadratically to the rotation in a few steps (most in 4–5, a few
    ill-conditioned ones in up to ~9); ``S = Rᵀ G`` symmetrized. Matrices with ``det G <= 0``
    or not converged in :data:`POLAR_MAX_ITERATIONS` fall back to the SVD ``G = U Σ Vᵀ``:
    ``R = U D Vᵀ``, ``S = V D Σ Vᵀ`` with ``D = diag(1, 1, det(U Vᵀ))`` so that ``det R = +1``
    (bermano2014 §4.2 encodes rotation and stretch separately).

    The iteration is compiled, one matrix at a time (:func:`service.geometry.gradient_kernels.newton_rotations`;
    89k matrices: 0.26 → 0.05 s under load 8). Departure from the vectorized NumPy steps it
    replaced: the same operations in the same order, but ζ's cube root is libm's where
    NumPy's ``cbrt`` is its AVX-512 SIMD one (up to 3 ulp apart), so the rotations differ
    by at most 4.4e-16 (2 ulp of 1) on 200k random, ill-conditioned (condition 1e8) and
    mixed-sign matrices, and the same matrices take the SVD fallback.

    Parameters
    ----------
    G : (...,3,3) float

    Returns
    -------
    R : (...,3,3) float64   rotation, ``det R = +1``
    S : (...,3,3) float64   symmetric stretch; positive definite when ``det G > 0``
                            (for a reflection, ``det G < 0``, S has one negative eigenvalue)
    """
    from service.geometry.gradient_kernels import newton_rotations   # Numba: where it is used

    G = np.asarray(G, dtype=np.float64)
    shape = G.shape
    G = G.reshape(-1, 3, 3)
    R = np.empty((len(G), 9))
    fallback = newton_rotations(np.ascontiguousarray(G.reshape(-1, 9)), POLAR_TOLERANCE,
                                POLAR_MAX_ITERATIONS, R)
    R = R.reshape(-1, 3, 3)
    S = np.swapaxes(R, -1, -2) @ G
    if fallback.any():
        R[fallback], S[fallback] = _polar_svd(G[fallback])
    S = 0.5 * (S + np.swapaxes(S, -1, -2))
    return R.reshape(shape), S.reshape(shape)


#: Newton steps of :func:`polar_decomposition` before the SVD fallback (a gradient with a
#: condition number of 1e6 needs about 9)
POLAR_MAX_ITERATIONS = 20
#: largest entry change of a converged Newton step; quadratic convergence puts the
#: rotation's error at about its square, far below rounding
POLAR_TOLERANCE = 1e-9


def _cofactors(X: np.ndarray) -> np.ndarray:
    """Cofactor matrices (9,k) of 3×3 matrices (9,k), entry-major: ``X⁻ᵀ = cof / det X``."""
    return np.stack([
        X[4] * X[8] - X[5] * X[7], X[5] * X[6] - X[3] * X[8], X[3] * X[7] - X[4] * X[6],
        X[2] * X[7] - X[1] * X[8], X[0] * X[8] - X[2] * X[6], X[1] * X[6] - X[0] * X[7],
        X[1] * X[5] - X[2] * X[4], X[2] * X[3] - X[0] * X[5], X[0] * X[4] - X[1] * X[3],
    ])


def _polar_svd(G: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Polar factors of (k,3,3) matrices by the SVD, R proper (see :func:`polar_decomposition`)."""
    U, sig, Vt = np.linalg.svd(G)
    d = np.sign(np.linalg.det(U @ Vt))
    d = np.where(d == 0, 1.0, d)
    U[..., :, 2] *= d[..., None]
    sig[..., 2] *= d
    R = U @ Vt
    S = np.swapaxes(Vt, -1, -2) @ (sig[..., :, None] * Vt)
    return R, S


def _hat(w: np.ndarray) -> np.ndarray:
    """Cross-product matrices (...,3,3) of vectors w (...,3)."""
    z = np.zeros(w.shape[:-1])
    return np.stack([
        np.stack([z, -w[..., 2], w[..., 1]], axis=-1),
        np.stack([w[..., 2], z, -w[..., 0]], axis=-1),
        np.stack([-w[..., 1], w[..., 0], z], axis=-1),
    ], axis=-2)


def rotation_exp(w: np.ndarray) -> np.ndarray:
    """Rotation matrices from axis-angle vectors (Rodrigues' formula).

    ``R = I + (sin θ/θ) [w]× + ((1 - cos θ)/θ²) [w]×²``, θ = ‖w‖ (radians), with Taylor series
    for θ < 1e-4 so it is exact to rounding near 0; well conditioned up to and past π.

    Parameters
    ----------
    w : (...,3) float   axis × angle

    Returns
    -------
    R : (...,3,3) float64
    """
    w = np.asarray(w, dtype=np.float64)
    th2 = np.einsum("...i,...i->...", w, w)
    th = np.sqrt(th2)
    small = th < 1e-4
    ths = np.where(small, 1.0, th)
    a = np.where(small, 1.0 - th2 / 6.0 + th2 * th2 / 120.0, np.sin(ths) / ths)
    b = np.where(small, 0.5 - th2 / 24.0 + th2 * th2 / 720.0, (1.0 - np.cos(ths)) / (ths * ths))
    K = _hat(w)
    eye = np.broadcast_to(np.eye(3), K.shape)
    return eye + a[..., None, None] * K + b[..., None, None] * (K @ K)


def rotation_log(R: np.ndarray) -> np.ndarray:
    """Axis-angle vectors of rotation matrices, angle in [0, π].

    Inverse of :func:`rotation_exp`. The angle comes from
    ``θ = atan2(‖a‖, (tr R - 1)/2)`` with ``a = vee(R - Rᵀ)/2 = sin θ · k``. The axis is
    ``a / sin θ`` (series ``θ/sin θ`` near 0), except near π (cos θ < -0.9) where sin θ loses
    precision: there it is read from the symmetric part ``(R + Rᵀ)/2 - cos θ I = (1 - cos θ) k kᵀ``
    (its largest column), with the sign taken from a. At exactly π, ±k are both valid logs.

    Parameters
    ----------
    R : (...,3,3) float   rotations (orthonormal, det +1)

    Returns
    -------
    w : (...,3) float64   axis × angle, ``‖w‖ <= π``
    """
    R = np.asarray(R, dtype=np.float64)
    a = 0.5 * np.stack([R[..., 2, 1] - R[..., 1, 2],
                        R[..., 0, 2] - R[..., 2, 0],
                        R[..., 1, 0] - R[..., 0, 1]], axis=-1)
    s = np.linalg.norm(a, axis=-1)
    c = 0.5 * (np.trace(R, axis1=-2, axis2=-1) - 1.0)
    th = np.arctan2(s, c)
    # generic branch: w = a θ / sin θ
    small = s < 1e-8
    scale = np.where(small, 1.0 + th * th / 6.0, th / np.where(small, 1.0, s))
    w = a * scale[..., None]
    # near π: axis from the symmetric part
    near_pi = c < -0.9
    if np.any(near_pi):
        Rn, an, cn, thn = R[near_pi], a[near_pi], c[near_pi], th[near_pi]
        B = 0.5 * (Rn + np.swapaxes(Rn, -1, -2)) - cn[:, None, None] * np.eye(3)
        j = np.argmax(np.diagonal(B, axis1=-2, axis2=-1), axis=-1)
        col = np.take_along_axis(B, j[:, None, None], axis=-1)[..., 0]   # (k,3)
        k = col / np.linalg.norm(col, axis=-1, keepdims=True)
        sgn = np.sign(np.einsum("ki,ki->k", k, an))
        k *= np.where(sgn == 0, 1.0, sgn)[:, None]
        w[near_pi] = k * thn[:, None]
    return w


def encode(G: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(log R, S) encoding of deformation gradients, bermano2014 §4.2 / §5.4.

    Parameters
    ----------
    G : (...,3,3) float

    Returns
    -------
    w : (...,3) float64    rotation log (axis × angle)
    s : (...,6) float64    upper triangle of S: ``S00, S01, S02, S11, S12, S22``
    """
    R, S = polar_decomposition(G)
    iu = np.triu_indices(3)
    return rotation_log(R), S[..., iu[0], iu[1]]


def decode(w: np.ndarray, s: np.ndarray) -> np.ndarray:
    """Inverse of :func:`encode`: ``G = exp(w) S`` from (...,3) logs and (...,6) stretches.

    Rodrigues' formula as :func:`rotation_exp` in the form ``exp(w) = c I + a [w]× + b w wᵀ``
    (``[w]×² = w wᵀ − θ² I``, ``c = 1 − b θ²``), written out entry by entry over arrays of
    all the matrices (entry-major), and the product with the symmetric S likewise: the
    per-frame compose of a shape-space enhancement (bermano2014 §5.4) decodes every
    triangle's blended detail, and on 89k triangles this took 14 ms where the stacked
    3×3 products took 37 ms; it agrees with ``rotation_exp(w) @ S`` to 4.4e-16. Compiled, one
    matrix at a time, the same operations in the same order
    (:func:`service.geometry.gradient_kernels.decode_rows`: bit for bit, 47 → 4.5 ms under
    load 8).
    """
    from service.geometry.gradient_kernels import decode_rows   # Numba: where it is used

    w = np.asarray(w, dtype=np.float64)
    s = np.asarray(s, dtype=np.float64)
    lead = np.broadcast_shapes(w.shape[:-1], s.shape[:-1])
    w = np.ascontiguousarray(np.broadcast_to(w, lead + (3,)).reshape(-1, 3))
    s = np.ascontiguousarray(np.broadcast_to(s, lead + (6,)).reshape(-1, 6))
    out = np.empty((len(w), 9))
    decode_rows(w, s, out)
    return out.reshape(lead + (3, 3))


# --------------------------------------------------------------------------- inverse

class GradientOperator:
    """Per-triangle gradient of piecewise-linear fields on a rest mesh.

    ``D`` is (3m, n) sparse: row ``3t + d`` gives component d (x, y, z) of the gradient of a
    per-vertex scalar field on triangle t, ``∇f_t = Σ_i f_i ∇φ_i`` with the hat-function
    gradients ``∇φ_i = (n_t × e_i) / (2 A_t)`` (e_i the edge opposite i, counter-clockwise).
    The gradients lie in the rest triangle's plane; ``Dᵀ W D = -L`` (the cotangent
    Laplacian of :mod:`service.geometry.laplacian`) with ``W = diag(A_t)`` per row.

    Parameters
    ----------
    V0 : (n,3) float   rest vertices (mm)
    F : (m,3) int      triangles, non-degenerate in V0

    Attributes
    ----------
    D : (3m,n) sparse CSR, 1/mm
    areas : (m,) float, mm²
    normals : (m,3) float, unit
    """

    def __init__(self, V0: np.ndarray, F: np.ndarray):
        V0 = np.asarray(V0, dtype=np.float64)
        F = np.asarray(F, dtype=np.int64)
        n, m = len(V0), len(F)
        P = V0[F]
        nrm = np.cross(P[:, 1] - P[:, 0], P[:, 2] - P[:, 0])
        dbl = np.linalg.norm(nrm, axis=1)                       # 2 A_t
        if np.any(dbl <= 0):
            raise ValueError(f"{int(np.sum(dbl <= 0))} degenerate triangles in the rest mesh")
        N = nrm / dbl[:, None]
        opp = np.roll(P, -2, axis=1) - np.roll(P, -1, axis=1)   # e_i = v_{i+2} - v_{i+1}
        grad = np.cross(N[:, None, :], opp) / dbl[:, None, None]   # (m,3 corners,3 dims)
        rows = (3 * np.arange(m)[:, None, None] + np.arange(3)[None, None, :])
        rows = np.broadcast_to(rows, (m, 3, 3))
        cols = np.broadcast_to(F[:, :, None], (m, 3, 3))
        self.D = sp.csr_matrix((grad.ravel(), (rows.ravel(), cols.ravel())), shape=(3 * m, n))
        self.areas = 0.5 * dbl
        self.normals = N
        self.n, self.m = n, m

    def jacobian(self, X: np.ndarray) -> np.ndarray:
        """Per-triangle Jacobians (m,C,3) of per-vertex fields X (n,C): row k = ∇X[:,k]."""
        X = np.asarray(X, dtype=np.float64)
        return (self.D @ X).reshape(self.m, 3, -1).transpose(0, 2, 1)

    def target_gradients(self, G: np.ndarray) -> np.ndarray:
        """Target gradients (3m,3) for the least squares ``‖D x - g‖²`` from 3×3 matrices.

        Row k of ``G_t`` is the gradient of coordinate k; only its component in the rest
        triangle's plane is reachable by a piecewise-linear field, so the target is
        ``G_t (I - n_t n_tᵀ)``, laid out like ``D @ X`` (row ``3t + d``, column k).

        Parameters
        ----------
        G : (m,3,3) float   per-triangle deformation gradients (rest → target)
        """
        G = np.asarray(G, dtype=np.float64)
        Nn = self.normals
        Gp = G - (G @ Nn[:, :, None]) * Nn[:, None, :]          # G (I - n nᵀ)
        return Gp.transpose(0, 2, 1).reshape(3 * self.m, 3)


def boundary_laplacian_1d(F: np.ndarray, n: int) -> sp.csr_matrix:
    """Uniform 1D Laplacian along the boundary loops, (b, n) sparse, one row per boundary vertex.

    ``(L_b x)_i = x_i - mean(x_j : j a boundary-edge neighbour of i)``, i.e.
    ``x_i - (x_prev + x_next)/2`` on a manifold boundary loop. Rows follow the sorted
    boundary vertex indices (see :func:`boundary_vertex_indices`).
    """
    E, count = edge_face_counts(np.asarray(F, dtype=np.int64))
    Eb = E[count == 1]
    bverts = np.unique(Eb)
    ij = (np.r_[Eb[:, 0], Eb[:, 1]], np.r_[Eb[:, 1], Eb[:, 0]])
    A = sp.coo_matrix((np.ones(2 * len(Eb)), ij), shape=(n, n)).tocsr()
    A = A[bverts]
    deg = np.asarray(A.sum(axis=1)).ravel()
    sel = sp.csr_matrix((np.ones(len(bverts)), (np.arange(len(bverts)), bverts)),
                        shape=(len(bverts), n))
    return (sel - sp.diags(1.0 / deg) @ A).tocsr()


def boundary_vertex_indices(F: np.ndarray) -> np.ndarray:
    """Sorted indices (b,) of the boundary vertices: the rows of :func:`boundary_laplacian_1d`."""
    E, count = edge_face_counts(np.asarray(F, dtype=np.int64))
    return np.unique(E[count == 1])


class PoissonReconstruction:
    """Prefactored Poisson reconstruction of positions from per-triangle deformation gradients.

    bermano2014 §5.5 (after Botsch et al. 2006): positions x (n,3) minimizing

    ``E(x) = Σ_t A_t ‖∇x_t - T_t‖²  +  w Σ_{i ∈ ∂} ‖(L_b x)_i - (L_b x_ref)_i‖²``

    where ``∇`` is the rest mesh's :class:`GradientOperator`, ``T_t = G_t (I - n_t n_tᵀ)`` the
    target gradients from 3×3 matrices ``G_t``, ``L_b`` the uniform 1D Laplacian along the
    boundary loops and ``x_ref`` a reference mesh (optional term, ``boundary_weight = w``).
    Normal equations ``(Dᵀ W D + w L_bᵀ L_b) x = Dᵀ W g + w L_bᵀ L_b x_ref``: the matrix
    depends only on the rest mesh, so it is factored once and every frame costs one
    back-substitution with three right-hand sides (x, y, z).

    The energy is invariant to translation (per connected component), fixed by pinning:
    ``pinned`` vertices are eliminated and set to given positions (default: one vertex per
    connected component, the lowest index, at its *rest* position). With a single pin per
    component the result is the least-squares mesh translated so the pin sits where asked;
    more pins turn it into a constrained solve.

    Parameters
    ----------
    V0 : (n,3) float          rest mesh (mm); the operator's geometry
    F : (m,3) int             triangles
    pinned : (p,) int | None  vertices fixed in every solve
    boundary_weight : float   w, ``0`` disables the boundary term; bermano2014 uses 0.05
                              (:data:`BOUNDARY_WEIGHT`)

    Notes
    -----
    As in the paper, the operator is the *rest* (neutral) mesh's, not the frame's: gradients
    are expressed relative to the rest triangles, so this is exact, not an approximation,
    for targets that came from :func:`deformation_gradients` with ``V0`` as the rest.
    The paper minimizes "the 1D Laplacian term along the mesh boundaries"; here the term
    matches the boundary Laplacian of ``x_ref`` (pass the low-frequency input frame), which
    reduces to the paper's literal zero target for a reference with straight boundaries.
    Without an ``x_ref`` the rest mesh's boundary Laplacian is the target. Both terms are
    independent of the length unit (cotangent weights vs. 1D-Laplacian weights, both O(1)
    matrix entries). At w = 0.05 the term is gentle: on the ICT rig, a reference that
    contradicts the target gradients all along the boundary pulls the boundary's 1D
    Laplacian ~1.5 % of the way toward it (w = 100: ~50 %); it damps small boundary
    wiggles from blended gradients rather than overriding them.
    """

    def __init__(self, V0: np.ndarray, F: np.ndarray, pinned: np.ndarray | None = None,
                 boundary_weight: float = 0.0):
        V0 = np.asarray(V0, dtype=np.float64)
        F = np.asarray(F, dtype=np.int64)
        n = len(V0)
        self.V0, self.F, self.n = V0, F, n
        self.grad = GradientOperator(V0, F)
        D, a = self.grad.D, np.repeat(self.grad.areas, 3)
        self._DtW = (D.T @ sp.diags(a)).tocsr()                 # (n,3m)
        A = (self._DtW @ D).tocsr()
        self.boundary_weight = float(boundary_weight)
        if self.boundary_weight < 0:
            raise ValueError(f"boundary_weight must be >= 0, got {boundary_weight}")
        if self.boundary_weight > 0:
            self._Lb = boundary_laplacian_1d(F, n)
            self._LbtLb = (self._Lb.T @ self._Lb).tocsr()
            A = A + self.boundary_weight * self._LbtLb
            self._delta_rest = self._Lb @ V0
        if pinned is None:
            used = np.zeros(n, dtype=bool)
            used[F.ravel()] = True
            ncomp, label = connected_components(adjacency_matrix(F, n), directed=False)
            first = np.full(ncomp, n)
            np.minimum.at(first, label[used], np.flatnonzero(used))
            pinned = np.r_[first[first < n], np.flatnonzero(~used)]
        self.pinned = np.unique(np.asarray(pinned, dtype=np.int64))
        free = np.ones(n, dtype=bool)
        free[self.pinned] = False
        self.free = np.flatnonzero(free)
        A = A.tocsr()
        self._A_fp = A[self.free][:, self.pinned]
        self._factor = factorize(A[self.free][:, self.free], spd=True, backend="cholmod")

    def solve(self, G: np.ndarray, pinned_positions: np.ndarray | None = None,
              boundary_reference: np.ndarray | None = None) -> np.ndarray:
        """Positions whose gradients best match ``G``.

        Parameters
        ----------
        G : (m,3,3) or (B,m,3,3) float   per-triangle deformation gradients w.r.t. the rest
                                         mesh (e.g. from :func:`deformation_gradients`)
        pinned_positions : (p,3) or (B,p,3) float | None   where the pins go (default: rest)
        boundary_reference : (n,3) or (B,n,3) float | None  x_ref of the boundary term
                                         (default: the rest mesh); ignored when w = 0

        Returns
        -------
        X : (n,3) or (B,n,3) float64, mm
        """
        G = np.asarray(G, dtype=np.float64)
        batched = G.ndim == 4
        Gb = G if batched else G[None]
        B = len(Gb)
        if Gb.shape[1:] != (self.grad.m, 3, 3):
            raise ValueError(f"G must be ({self.grad.m},3,3) or (B,{self.grad.m},3,3), got {G.shape}")
        # a batch's sparse products take all 3B right-hand sides at once (columns frame-major,
        # 3b + k; CSR products treat columns independently); the factor solves three columns
        # (one frame) at a time: CHOLMOD's supernodal solve of more columns rounds
        # differently (~2e-15 relative) and saved only ~10 % at level 1
        T = np.stack([self.grad.target_gradients(g) for g in Gb], axis=1)   # (3m,B,3)
        rhs = self._DtW @ T.reshape(3 * self.grad.m, 3 * B)                  # (n,3B)
        if self.boundary_weight > 0:
            if boundary_reference is None:
                delta = np.tile(self._delta_rest, (1, B))
            else:
                ref = np.asarray(boundary_reference, dtype=np.float64)
                ref = np.broadcast_to(ref, (B,) + ref.shape[-2:]) if ref.ndim == 2 else ref
                delta = self._Lb @ np.moveaxis(ref, 0, 1).reshape(self.n, 3 * B)
            rhs = rhs + self.boundary_weight * (self._Lb.T @ delta)
        p = len(self.pinned)
        if pinned_positions is None:
            xp = np.tile(self.V0[self.pinned], (1, B))
        else:
            xp = np.asarray(pinned_positions, dtype=np.float64)
            xp = (np.moveaxis(xp, 0, 1).reshape(p, 3 * B) if xp.ndim == 3
                  else np.tile(xp.reshape(p, 3), (1, B)))
        X = np.empty((self.n, 3 * B))
        X[self.pinned] = xp
        free = rhs[self.free] - self._A_fp @ xp
        for b in range(B):
            X[self.free, 3 * b:3 * b + 3] = self._factor(free[:, 3 * b:3 * b + 3])
        X = np.moveaxis(X.reshape(self.n, B, 3), 1, 0)
        return np.ascontiguousarray(X) if batched else np.ascontiguousarray(X[0])

    __call__ = solve


def poisson_reconstruct(V0: np.ndarray, F: np.ndarray, G: np.ndarray,
                        pinned: np.ndarray | None = None,
                        pinned_positions: np.ndarray | None = None,
                        boundary_weight: float = 0.0,
                        boundary_reference: np.ndarray | None = None) -> np.ndarray:
    """One-shot :class:`PoissonReconstruction` (factor, then solve).

    Keep a :class:`PoissonReconstruction` instead when solving many frames on one rest mesh.

    Parameters
    ----------
    V0 : (n,3) float    rest mesh (mm)
    F : (m,3) int
    G : (m,3,3) or (B,m,3,3) float   deformation gradients w.r.t. V0

    Returns
    -------
    X : (n,3) or (B,n,3) float64
    """
    rec = PoissonReconstruction(V0, F, pinned=pinned, boundary_weight=boundary_weight)
    return rec.solve(G, pinned_positions=pinned_positions, boundary_reference=boundary_reference)
