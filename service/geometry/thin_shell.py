"""Linear thin-shell deformation driven by handle vertices (bickel2008 §4, eq. 1).

The large-scale displacement ``u`` of a face from the displacements ``u_H`` of H handle
vertices (mocap markers) minimizes a quadratic stretching + bending energy, whose
Euler-Lagrange equations are (bickel2008 eq. 1)

    −k_s Δu + k_b Δ²u = 0   on free vertices,   u = u_H   on handles.

Discretization
--------------
With the cotangent Laplacian ``L`` (negative semi-definite, [MDSB03]) and the lumped mass
matrix ``M`` (mixed Voronoi areas of [MDSB03] by default; ``Δ ≈ M⁻¹L``), the equations
multiplied by ``M`` give the symmetric positive semi-definite operator

    K = −k_s L + k_b L M⁻¹ L          (n,n), units 1 (k_s) and mm⁻² (k_b)

which is split into the free and handle blocks of bickel2008 §4: ``A = K[free,free]``,
``A_H = K[free,handles]``, ``A u + A_H u_H = 0``; ``B = −A⁻¹ A_H`` is the precomputed basis.
``A`` is symmetric positive-definite as soon as every connected component has a handle.

Defaults
--------
Only the ratio ``k_b / k_s`` matters (scaling K does not change the solution), and it is
the square of a length ``ℓ = sqrt(k_b / k_s)``: below ℓ the shell bends (smooth, C¹-like
bumps around a handle), beyond ℓ it stretches (a handle's influence decays like
K₀(r/ℓ)). Membrane-dominated settings (ℓ ≲ marker spacing) put a cusp at every handle
whose width shrinks with the mesh resolution, because a point constraint of the Laplace
equation is log-singular; pure bending (ℓ → ∞) extrapolates linearly away from the
markers. The defaults ``KS = 1``, ``KB = 400 mm²`` (ℓ = 20 mm, ≈ 1.3 × the 15 mm median
spacing of 150 markers on a face) were chosen by reconstructing 8 ICT-rig blendshapes
(jawOpen, smile, brows, blink, puff, pucker, sneer) from their displacements at 150
markers (level 0, RMS error over the narrow face | rest of the face | max |u| on head and
neck, where the truth is ≤ 1.6 mm):

=========  =============  =============  ==============
ℓ (mm)     narrow face    rest of face   head & neck
=========  =============  =============  ==============
1          1.08 mm        1.67 mm        8.9 mm
5          0.78           1.45           8.1
10         0.76           1.23           6.9
20         0.77           0.97           4.4
30         0.78           0.93           4.8
1000       0.78           1.61           13.2
=========  =============  =============  ==============

At ℓ = 20 mm a single pushed marker makes a smooth bump (its 1-ring follows within 2% of
pure bending; ℓ = 1 mm makes a cusp), pinned in ``tests/geometry/test_thin_shell.py``.

Departures from the paper
-------------------------
- The paper gives no stiffness values; see Defaults.
- A linear shell is not rotation-invariant: a rigid rotation of all handles is reproduced
  only approximately on a curved surface, because the cotangent Laplacian of the
  coordinate functions is the mean-curvature normal (``L x ≈ M Δx = 2 M H n``, not 0)
  and because free-boundary rows of L do not vanish on linear functions (a 1° rotation
  of 60 face markers leaves ≈ 0.4 mm error on the face). Translations are
  reproduced exactly (L 1 = 0). Remove rigid head motion first
  (:mod:`service.geometry.rigid`), as bickel2008 and DESIGN.md do.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import connected_components

from service.geometry.laplacian import cotangent_laplacian, mass_matrix
from service.geometry.sparse_solve import Factor, factorize
from service.geometry.topology import adjacency_matrix

#: default stretching stiffness (dimensionless; only kb/ks matters)
KS = 1.0
#: default bending stiffness, mm² (ℓ = sqrt(KB/KS) = 20 mm for faces in millimetres)
KB = 400.0
#: right-hand sides per solve when building the basis (bounds the dense work arrays)
BASIS_CHUNK = 64


def thin_shell_operator(
    V: np.ndarray, F: np.ndarray, ks: float = KS, kb: float = KB, mass: str = "voronoi"
) -> sp.csr_matrix:
    """Discrete thin-shell operator ``K = −k_s L + k_b L M⁻¹ L`` (bickel2008 §4, eq. 1).

    Parameters
    ----------
    V : (n,3) float   rest vertices, mm
    F : (m,3) int     triangles
    ks : float        stretching stiffness, ≥ 0
    kb : float        bending stiffness, mm², ≥ 0 (``ks + kb > 0``)
    mass : str        lumped mass for M: ``"voronoi"`` (mixed Voronoi, [MDSB03], libigl's
                      default) or ``"barycentric"``

    Returns
    -------
    K : (n,n) sparse CSR float64, symmetric positive semi-definite, ``K @ 1 = 0``

    Raises
    ------
    ValueError
        negative stiffness, both zero, or a vertex used by a triangle has zero mass
        (all its triangles degenerate).
    """
    if ks < 0 or kb < 0 or ks + kb <= 0:
        raise ValueError(f"need ks >= 0, kb >= 0, ks + kb > 0; got ks={ks}, kb={kb}")
    V = np.asarray(V, dtype=np.float64)
    F = np.asarray(F, dtype=np.int64)
    n = len(V)
    L = cotangent_laplacian(V, F)
    K = -ks * L if ks > 0 else sp.csr_matrix((n, n))
    if kb > 0:
        m = mass_matrix(V, F, kind=mass).diagonal()
        used = np.zeros(n, dtype=bool)
        used[F.ravel()] = True
        bad = np.flatnonzero(used & ~(m > 0))
        if len(bad):
            raise ValueError(f"{len(bad)} vertices have zero area (degenerate triangles), "
                             f"e.g. {bad[:10].tolist()}")
        inv_m = np.divide(1.0, m, out=np.zeros(n), where=m > 0)
        K = K + kb * (L @ sp.diags(inv_m) @ L)
    K = K.tocsr()
    return ((K + K.T) * 0.5).tocsr()  # exact symmetry despite round-off in the product


def _check_handles(handles: np.ndarray, n: int) -> np.ndarray:
    """Validated handle indices (h,) int64: 1-D, integer, in range, no duplicates."""
    h = np.asarray(handles)
    if h.ndim != 1 or h.size == 0:
        raise ValueError(f"handles must be a non-empty 1-D index array, got shape {h.shape}")
    if not np.issubdtype(h.dtype, np.integer):
        raise ValueError(f"handles must be integer vertex indices, got dtype {h.dtype}")
    h = h.astype(np.int64)
    out = np.flatnonzero((h < 0) | (h >= n))
    if len(out):
        raise ValueError(f"handle indices out of range [0, {n}): {h[out][:20].tolist()}"
                         f"{' ...' if len(out) > 20 else ''} (at positions {out[:20].tolist()})")
    uniq, counts = np.unique(h, return_counts=True)
    dup = uniq[counts > 1]
    if len(dup):
        raise ValueError(f"duplicated handle vertices: {dup[:20].tolist()}"
                         f"{' ...' if len(dup) > 20 else ''}")
    return h


def _check_components(F: np.ndarray, n: int, handles: np.ndarray) -> None:
    """Raise if a connected component (or an unreferenced vertex) has no handle: A singular."""
    ncomp, label = connected_components(adjacency_matrix(F, n), directed=False)
    has_handle = np.zeros(ncomp, dtype=bool)
    has_handle[label[handles]] = True
    if not has_handle.all():
        sizes = np.bincount(label, minlength=ncomp)
        missing = np.flatnonzero(~has_handle)
        first = [int(np.flatnonzero(label == c)[0]) for c in missing[:5]]
        desc = ", ".join(f"{sizes[c]} vertices (e.g. vertex {v})" for c, v in zip(missing[:5], first))
        raise ValueError(
            f"{len(missing)} connected component(s) have no handle, so the thin-shell system is "
            f"singular: {desc}{' ...' if len(missing) > 5 else ''}; add a handle to each "
            f"component or remove unreferenced vertices"
        )


def thin_shell_system(
    V: np.ndarray, F: np.ndarray, handles: np.ndarray, ks: float = KS, kb: float = KB,
    mass: str = "voronoi",
) -> tuple[sp.csc_matrix, sp.csc_matrix, np.ndarray]:
    """Free/handle blocks of the thin-shell system (bickel2008 §4, ``(A A_H)(u; u_H) = 0``).

    Parameters
    ----------
    V : (n,3) float      rest vertices, mm
    F : (m,3) int        triangles
    handles : (h,) int   constrained vertex indices (marker sites), distinct, in [0, n)
    ks, kb, mass         see :func:`thin_shell_operator`

    Returns
    -------
    A : (n-h,n-h) sparse CSC   ``K[free,free]``, symmetric positive-definite
    A_H : (n-h,h) sparse CSC   ``K[free,handles]``, columns in the order of ``handles``
    free : (n-h,) int          free vertex indices, ascending

    Raises
    ------
    ValueError
        handles out of range, duplicated or empty; a connected component without a
        handle (A would be singular; the message gives the component's size).
    """
    V = np.asarray(V, dtype=np.float64)
    F = np.asarray(F, dtype=np.int64)
    n = len(V)
    h = _check_handles(handles, n)
    _check_components(F, n, h)
    K = thin_shell_operator(V, F, ks, kb, mass).tocsc()
    is_handle = np.zeros(n, dtype=bool)
    is_handle[h] = True
    free = np.flatnonzero(~is_handle)
    Kf = K[:, free].tocsr()
    A = Kf[free].tocsc()
    A_H = K[:, h].tocsr()[free].tocsc()
    return A, A_H, free


def _as_frames(u_H: np.ndarray, h: int) -> tuple[np.ndarray, bool]:
    """(F,h,3) float64 view of (h,3) or (F,h,3) handle displacements, and whether batched."""
    u = np.asarray(u_H, dtype=np.float64)
    if u.ndim == 2 and u.shape == (h, 3):
        return u[None], False
    if u.ndim == 3 and u.shape[1:] == (h, 3):
        return u, True
    raise ValueError(f"handle displacements must be ({h},3) or (frames,{h},3), got {u.shape}")


class ThinShellSolver:
    """Prefactored thin shell of one actor: per frame, handle displacements → all vertices.

    Factorizes ``A`` once (bickel2008 §4 as in [BBA*07], sparse factorization) and solves
    ``A u = −A_H u_H`` per frame or batch of frames; :meth:`basis` turns the same factor
    into the precomputed ``B`` of bickel2008 §4.

    Parameters
    ----------
    V : (n,3) float      rest vertices, mm
    F : (m,3) int        triangles
    handles : (h,) int   constrained vertex indices
    ks, kb, mass         see :func:`thin_shell_operator`

    Attributes
    ----------
    n : int              vertex count
    handles : (h,) int   as given (the order of the columns of ``u_H``)
    free : (n-h,) int    free vertices
    A_H : (n-h,h) sparse CSC
    factor : Factor      factorization of ``A``
    """

    def __init__(self, V: np.ndarray, F: np.ndarray, handles: np.ndarray,
                 ks: float = KS, kb: float = KB, mass: str = "voronoi") -> None:
        A, A_H, free = thin_shell_system(V, F, handles, ks, kb, mass)
        self.n = len(V)
        self.handles = np.asarray(handles, dtype=np.int64)
        self.free = free
        self.A_H = A_H
        self.factor: Factor = factorize(A, spd=True)

    def deform(self, u_H: np.ndarray) -> np.ndarray:
        """Displacements of all vertices from handle displacements (bickel2008 eq. 1).

        Parameters
        ----------
        u_H : (h,3) or (frames,h,3) float   handle displacements, mm

        Returns
        -------
        u : (n,3) or (frames,n,3) float64   displacements, mm; ``u[handles] == u_H`` exactly
        """
        h = len(self.handles)
        U, batched = _as_frames(u_H, h)
        nf = len(U)
        rhs = -(self.A_H @ U.transpose(1, 0, 2).reshape(h, 3 * nf))      # (n-h, 3F)
        x = self.factor.solve(rhs)
        out = np.empty((nf, self.n, 3))
        out[:, self.free] = x.reshape(-1, nf, 3).transpose(1, 0, 2)
        out[:, self.handles] = U
        return out if batched else out[0]

    def basis(self, dtype: np.dtype = np.float64, chunk: int = BASIS_CHUNK) -> np.ndarray:
        """Precomputed basis ``B`` (bickel2008 §4): full displacement ``u = B @ u_H``.

        Parameters
        ----------
        dtype : float dtype   storage dtype of B (computed in float64); float32 halves the
                              memory and the per-frame memory traffic of :func:`apply_basis`
        chunk : int           handle columns solved at once (bounds the dense work arrays
                              to ``(n-h) × chunk`` float64)

        Returns
        -------
        B : (n,h) dense, Fortran order   rows of free vertices ``−A⁻¹A_H``; the row of
                                         handle k is the unit row e_k. Column-major
                                         because ``B.T`` is then a C-contiguous (h,n),
                                         the fast operand of :func:`apply_basis`.
        """
        h = len(self.handles)
        B = np.zeros((self.n, h), dtype=dtype, order="F")
        B[self.handles, np.arange(h)] = 1
        for c0 in range(0, h, chunk):
            cols = slice(c0, min(c0 + chunk, h))
            rhs = -self.A_H[:, cols].toarray()
            B[self.free, cols] = self.factor.solve(rhs)
        return B


def thin_shell_basis(
    V: np.ndarray, F: np.ndarray, handles: np.ndarray, ks: float = KS, kb: float = KB,
    dtype: np.dtype = np.float64, mass: str = "voronoi", chunk: int = BASIS_CHUNK,
) -> np.ndarray:
    """Precomputed linear thin-shell basis (bickel2008 §4, eq. 1 and ``B = −A⁻¹A_H``).

    Solves −k_s Δu + k_b Δ²u = 0 with u fixed on the handles once per actor (one
    factorization of A, h right-hand sides in chunks), so that per frame ``u = B @ u_H``
    is one dense product (:func:`apply_basis`).

    Parameters
    ----------
    V : (n,3) float      rest vertices, mm
    F : (m,3) int        triangles
    handles : (h,) int   constrained vertex indices (marker sites)
    ks, kb, mass         see :func:`thin_shell_operator`
    dtype : float dtype  storage dtype (computed in float64)
    chunk : int          right-hand sides per solve

    Returns
    -------
    B : (n,h) dense, Fortran order   maps handle displacements (h,3) to displacements of
                      all vertices (n,3); rows of handle vertices are unit rows. 8·n·h bytes
                      in float64 (51 MiB for 45 k vertices and 150 handles), half in float32.
                      Keep the Fortran order when storing it (``np.save`` does).

    Notes
    -----
    Departs from the STYLE.md sketch, which returns only the (n-h,h) free rows: the full
    (n,h) form makes ``B @ u_H`` the whole displacement field with no scatter.
    """
    return ThinShellSolver(V, F, handles, ks, kb, mass).basis(dtype=dtype, chunk=chunk)


def apply_basis(B: np.ndarray, u_H: np.ndarray) -> np.ndarray:
    """Displacements ``u = B @ u_H`` for one frame or a batch of frames (bickel2008 §4).

    Parameters
    ----------
    B : (n,h) float                     from :func:`thin_shell_basis` (Fortran order is
                                        fastest; C order works)
    u_H : (h,3) or (frames,h,3) float   handle displacements, mm

    Returns
    -------
    u : (n,3) or (frames,n,3), dtype of B, C order   displacements, mm

    Notes
    -----
    ``u_H`` is cast to B's dtype (never the reverse, which would copy B), and a batch is
    one GEMM ``(n,h) @ (h,3·frames)``, which reads B once for all frames. For a
    Fortran-ordered B the product is evaluated transposed, ``(3·frames,h) @ Bᵀ`` with
    ``Bᵀ`` a C-contiguous (h,n): OpenBLAS runs this skinny product 2-3× faster than
    ``B @ u_H`` with B in C order (it streams B instead of packing it), which matters
    because one frame is memory-bound on reading B (see benchmarks/thin_shell.py).
    """
    B = np.asarray(B)
    n, h = B.shape
    U, batched = _as_frames(u_H, h)
    nf = len(U)
    if B.flags.f_contiguous:
        rhs_t = np.ascontiguousarray(U.transpose(0, 2, 1).reshape(3 * nf, h), dtype=B.dtype)
        out = (rhs_t @ B.T).reshape(nf, 3, n).transpose(0, 2, 1)         # (F,n,3) view
    else:
        rhs = np.ascontiguousarray(U.transpose(1, 0, 2).reshape(h, 3 * nf), dtype=B.dtype)
        out = (B @ rhs).reshape(n, nf, 3).transpose(1, 0, 2)            # (F,n,3) view
    out = np.ascontiguousarray(out)
    return out if batched else out[0]


def handle_energy_matrix(V: np.ndarray, F: np.ndarray, B: np.ndarray, ks: float = KS,
                         kb: float = KB, mass: str = "voronoi") -> np.ndarray:
    """Thin-shell energy as a quadratic form of the handle displacements: ``G = Bᵀ K B``.

    For the minimizer ``u = B u_H`` of ``uᵀKu`` (bickel2008 eq. 1) the energy is
    ``u_Hᵀ G u_H``, so :func:`complete_handles` can drop handles exactly.

    Parameters
    ----------
    V : (n,3) float   rest vertices, mm;   F : (m,3) int
    B : (n,h) float   the basis of :func:`thin_shell_basis` for the same V, F, ks, kb, mass

    Returns
    -------
    G : (h,h) float64   symmetric positive semi-definite
    """
    K = thin_shell_operator(V, F, ks, kb, mass).tocsr()
    B = np.asarray(B, dtype=np.float64)
    G = B.T @ (K @ B)
    return 0.5 * (G + G.T)


def complete_handles(G: np.ndarray, u_H: np.ndarray) -> np.ndarray:
    """Fill unknown (NaN) handle displacements so that ``B @ u_H`` is the thin shell
    solved with the known handles only (missing markers: their constraints dropped).

    Minimizing ``u_Hᵀ G u_H`` over the unknown rows U with the known rows K fixed gives
    ``G_UU u_U = −G_UK u_K``: exact, an (|U|,|U|) solve instead of a new factorization.

    Parameters
    ----------
    G : (h,h) float             :func:`handle_energy_matrix`
    u_H : (h,3) float           handle displacements, NaN rows unknown

    Returns
    -------
    u_H : (h,3) float64         with the unknown rows filled (a copy)

    Raises
    ------
    ValueError   when no handle is known
    """
    u = np.array(u_H, dtype=np.float64)
    unknown = ~np.isfinite(u).all(axis=1)
    if not unknown.any():
        return u
    known = ~unknown
    if not known.any():
        raise ValueError("all handles are unknown; at least one is needed")
    G_UU = G[np.ix_(unknown, unknown)]
    rhs = -G[np.ix_(unknown, known)] @ u[known]
    u[unknown] = np.linalg.solve(G_UU, rhs)
    return u


# ---------------------------------------------------------------------- soft handle constraints
def as_frames(u_H: np.ndarray, h: int) -> tuple[np.ndarray, bool]:
    """(F,h,3) float64 copy of (h,3) or (F,h,3) per-handle (or per-marker) values (NaN
    allowed), and whether they were batched (the caller answers in the shape it was given).

    Raises ValueError for any other shape."""
    u = np.array(u_H, dtype=np.float64)
    if u.ndim == 2 and u.shape == (h, 3):
        return u[None], False
    if u.ndim == 3 and u.shape[1:] == (h, 3):
        return u, True
    raise ValueError(f"displacements must be ({h},3) or (frames,{h},3), got {u.shape}")


def marker_noise_ratio(noise_mm: float, prior_scale_mm: float) -> float:
    """λ = σ² / τ²: the weight of the shell prior against the marker data (MAP, see below).

    Parameters
    ----------
    noise_mm : float        σ ≥ 0, the markers' noise per coordinate, mm (0: interpolate)
    prior_scale_mm : float  τ > 0, the shell prior's scale, mm (:func:`shell_prior_scale`)
    """
    if not (noise_mm >= 0 and np.isfinite(noise_mm)):
        raise ValueError(f"marker noise must be finite and >= 0 mm, got {noise_mm}")
    if not (prior_scale_mm > 0 and np.isfinite(prior_scale_mm)):
        raise ValueError(f"the prior scale must be finite and > 0 mm, got {prior_scale_mm}")
    return float(noise_mm) ** 2 / float(prior_scale_mm) ** 2


def shell_prior_scale(G: np.ndarray, u_H: np.ndarray) -> float:
    """Scale τ (mm) of the shell prior ``p(u_H) ∝ exp(−u_Hᵀ G u_H / 2τ²)`` from samples.

    Empirical Bayes: for u_H drawn from that Gaussian (per coordinate, on the range of G),
    ``E[u_Hᵀ G u_H] = τ² · rank(G)``, so ``τ² = mean_t Σ_xyz u_tᵀ G u_t / (3 rank G)`` over
    sample displacements (e.g. the aligned training frames' handles; frames with a missing
    handle are skipped).

    Parameters
    ----------
    G : (h,h) float             :func:`handle_energy_matrix`
    u_H : (F,h,3) float         sample handle displacements, mm

    Returns
    -------
    tau : float, mm             > 0 (a floor of 1e-6 mm when the samples carry no energy)

    Raises
    ------
    ValueError   no complete sample frame
    """
    G = np.asarray(G, dtype=np.float64)
    u, _ = as_frames(u_H, len(G))
    u = u[np.isfinite(u).all(axis=(1, 2))]
    if not len(u):
        raise ValueError("no sample frame has every handle; cannot estimate the shell prior")
    ev = np.linalg.eigvalsh(G)
    rank = int(np.count_nonzero(ev > ev.max() * 1e-10)) if ev.max() > 0 else 0
    energy = np.einsum("fid,ij,fjd->", u, G, u) / len(u)
    return float(np.sqrt(max(energy / (3 * max(rank, 1)), 1e-12)))


def soft_handle_operator(G: np.ndarray, ratio: float) -> np.ndarray:
    """Precomputed soft solve of fully visible handles: ``P = (I + λ G)⁻¹`` (h,h).

    The MAP estimate of the true handle displacements u from noisy marker displacements m
    with Gaussian noise σ (mm, per coordinate) and the shell prior of
    :func:`shell_prior_scale` (scale τ) minimizes, per coordinate,

        u ᵀ G u / τ²  +  |u − m|² / σ²        ⇔    u ᵀ G u + w |u − m|²,  w = τ²/σ² = 1/λ,

    i.e. the thin-shell energy of bickel2008 §4 (eq. 1, as a quadratic form in the handles)
    plus a spring of stiffness w from each handle to its marker: ``u = w (G + w I)⁻¹ m =
    (I + λG)⁻¹ m``. λ = 0 is the paper's exact interpolation (P = I). G's null space (rigid
    translation, ``G 1 = 0``) passes unchanged: the filter only removes shell energy.

    Parameters
    ----------
    G : (h,h) float   :func:`handle_energy_matrix`
    ratio : float     λ = σ²/τ² ≥ 0 (:func:`marker_noise_ratio`)

    Returns
    -------
    P : (h,h) float64  symmetric, eigenvalues in (0, 1]
    """
    G = np.asarray(G, dtype=np.float64)
    if not (ratio >= 0 and np.isfinite(ratio)):
        raise ValueError(f"need a finite ratio >= 0, got {ratio}")
    h = len(G)
    P = np.linalg.solve(np.eye(h) + ratio * G, np.eye(h))
    return 0.5 * (P + P.T)


def soft_handles(G: np.ndarray, u_H: np.ndarray, ratio: float,
                 operator: np.ndarray | None = None) -> np.ndarray:
    """Handle displacements denoised by soft constraints (MAP of :func:`soft_handle_operator`).

    Visible rows (finite) are springs to their markers, missing rows (NaN) drop out of the
    data term: ``min u ᵀ G u + w Σ_visible |u_i − m_i|²``. With V the visible and U the
    missing handles the normal equations split into ``u_U = −G_UU⁻¹ G_UV u_V`` (the
    minimum-energy completion of :func:`complete_handles`) and

        (I + λ S) u_V = m_V,      S = G_VV − G_VU G_UU⁻¹ G_UV  (the Schur complement),

    the energy of the visible handles with the missing ones eliminated. This form is exact at
    λ = 0 (the hard solve: ``u_V = m_V``, then completion) and stable for every λ, unlike
    solving ``(G + wD) u = w D m`` with a large w.

    Parameters
    ----------
    G : (h,h) float                   :func:`handle_energy_matrix`
    u_H : (h,3) or (F,h,3) float      marker displacements at the handles, mm; NaN rows missing
    ratio : float                     λ = σ²/τ² ≥ 0 (:func:`marker_noise_ratio`)
    operator : (h,h) float, optional  :func:`soft_handle_operator` ``(G, ratio)``, for the
                                      frames with every handle visible (precomputed once)

    Returns
    -------
    u : same shape, float64, complete  (a copy)

    Raises
    ------
    ValueError   a frame with no visible handle
    """
    G = np.asarray(G, dtype=np.float64)
    h = len(G)
    u, batched = as_frames(u_H, h)
    missing = ~np.isfinite(u).all(axis=2)                                 # (F,h)
    full = ~missing.any(axis=1)
    if ratio == 0:
        out = u
    else:
        P = soft_handle_operator(G, ratio) if operator is None else operator
        out = u.copy()
        if full.any():
            out[full] = np.einsum("ij,fjd->fid", P, u[full])
    # frames with missing handles, grouped by their visibility pattern (one Schur solve each)
    if (~full).any():
        patterns, which = np.unique(missing[~full], axis=0, return_inverse=True)
        frames = np.flatnonzero(~full)
        for p, miss in enumerate(patterns):
            sel = frames[which.ravel() == p]
            vis = ~miss
            if not vis.any():
                raise ValueError("all handles are unknown; at least one is needed")
            G_UU, G_UV = G[np.ix_(miss, miss)], G[np.ix_(miss, vis)]
            C = np.linalg.solve(G_UU, G_UV)                                # (|U|,|V|)
            mV = u[np.ix_(sel, vis)]                                       # (k,|V|,3)
            if ratio:
                S = G[np.ix_(vis, vis)] - G_UV.T @ C
                S = 0.5 * (S + S.T)
                mV = np.einsum("ij,fjd->fid", np.linalg.inv(np.eye(int(vis.sum())) + ratio * S), mV)
            out[np.ix_(sel, vis)] = mV
            out[np.ix_(sel, miss)] = -np.einsum("ij,fjd->fid", C, mV)
    return out if batched else out[0]
