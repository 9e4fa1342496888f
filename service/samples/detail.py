"""Ground-truth fine detail of the sample actor, driven by local skin strain.

The detail is a deterministic, *nonlinear* function of how the skin around each point is
compressed or stretched by the expression (what ma2008 §4 and bickel2008 §5.1 learn):

* **expression wrinkles** at anatomical sites (forehead, glabella, crow's feet, under-eye,
  nasolabial folds, nose, chin). Each site has a static unit pattern (line furrows with a
  line direction, an envelope and per-line strengths) and buckles with the compression
  ``c = 1 − λ_a`` across its lines: amplitude ``A_max · tanh(√(max(c − c₀, 0) / c_s))``
  — zero below the threshold c₀ (and so at neutral), growing like the post-buckling
  amplitude of a compressed plate (∝ √(ε − ε_c)), saturating at A_max (≤ 2 mm);
* **pores**: a jittered grid in UV space (~1.4 mm spacing on the face), 0.05–0.2 mm deep,
  whose depth scales with the local area change ``J^-γ`` and whose footprint stretches
  with the skin (``λ^β`` along each direction, β > 1: the opening widens faster than the
  skin around it, and closes into a slit under compression);
* **albedo**: a skin base colour with redder cheeks, nose and lips, pore-scale darkening
  and melanin speckle, and blood-flow redness that rises with compression (blood pools in
  folds) and blanches with stretch (after Jimenez et al. 2010's dynamic facial colour).

Strain is the per-vertex area-averaged right Cauchy-Green tensor ``Q = ⟨F_tᵀF_t⟩`` of the
rig-resolution surface (F_t the triangle's deformation gradient on its tangent plane),
carried to the high-resolution mesh and to texels linearly: ``λ_a² = aᵀ Q a`` for a unit
tangent direction a of the rest surface.

Layout: :func:`surface_strain` returns tensors point-major in Voigt order, (…,n,6) with
components ``xx yy zz xy xz yz`` (what a sparse upsampling ``S @ Q`` wants); the per-point
functions take them component-major, tensors (6,k) and vectors (3,k), so that every
component is one contiguous array (3-5× faster on the ~0.7M texels of a 1024² map).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

from service.geometry.topology import vertex_face_adjacency

# pores
PORE_SPACING_UV = 1.0 / 260      # jittered-grid cell (≈ 1.4 mm on the face at 370 mm/uv)
PORE_RADIUS_MM = (0.18, 0.32)
PORE_DEPTH_MM = (0.05, 0.20)
PORE_SHAPE_BETA = 1.6            # footprint ∝ λ^β along each direction
PORE_DEPTH_GAMMA = 2.0           # depth ∝ J^-γ, J the local area ratio
# albedo (linear RGB)
SKIN_BASE = np.array([0.58, 0.40, 0.32])
REDNESS_ABSORPTION = np.array([0.0, 0.55, 0.45])


@dataclass(frozen=True)
class WrinkleSite:
    """One anatomical wrinkle site, in the rest (neutral, head-frame) pose.

    Attributes
    ----------
    name : str
    kind : ``"lines"`` (parallel furrows), ``"radial"`` (fan from ``centre``) or ``"fold"``
        (one deep furrow with a bulge on the ``across`` side)
    centre : (3,) float         mm, on the neutral surface
    along, across : (3,) float  unit directions of the lines and across them (head frame)
    extent : (2,) float         envelope σ along / across, mm
    wavelength : float          line spacing, mm (furrow width for a fold)
    amplitude : float           saturated furrow depth A_max, mm
    threshold, scale : float    buckling onset c₀ and compression scale c_s
    curvature : float           lines bend as ``x_across + curvature · x_along²`` (1/mm)
    """

    name: str
    kind: str
    centre: np.ndarray
    along: np.ndarray
    across: np.ndarray
    extent: tuple[float, float]
    wavelength: float
    amplitude: float
    threshold: float = 0.04
    scale: float = 0.15
    curvature: float = 0.0

    def response(self, compression: np.ndarray) -> np.ndarray:
        """Buckling amplitude (mm) for compression across the lines (1 − stretch)."""
        e = np.maximum(compression - self.threshold, 0.0)
        return self.amplitude * np.tanh(np.sqrt(e / self.scale))


def _unit(v) -> np.ndarray:
    v = np.asarray(v, dtype=np.float64)
    return v / np.linalg.norm(v)


def wrinkle_sites(neutral: np.ndarray, landmarks68: np.ndarray) -> list[WrinkleSite]:
    """The actor's wrinkle sites from its rig-resolution neutral (n0,3) and 68 landmarks.

    Axes: x to the actor's left, y up, z out of the face. Landmark 36 is the actor's right
    outer eye corner, 45 the left one (Multi-PIE numbering).
    """
    P = neutral[landmarks68]

    def snap(p):
        return neutral[np.argmin(np.linalg.norm(neutral - p, axis=1))]

    x, y = np.array([1.0, 0, 0]), np.array([0, 1.0, 0])
    sites = [
        WrinkleSite("forehead", "lines", snap((P[19] + P[24]) / 2 + [0, 30, 0]), x, y,
                    (42.0, 15.0), 10.0, 1.3, threshold=0.05, scale=0.18, curvature=0.004),
        WrinkleSite("glabella", "lines", snap((P[21] + P[22]) / 2 + [0, -3, 0]), y, x,
                    (9.0, 8.0), 6.5, 1.0, threshold=0.04, scale=0.12),
        WrinkleSite("chin", "lines", snap(P[57] + [0, -17, 0]), x, y,
                    (13.0, 7.0), 7.0, 0.7, threshold=0.05, scale=0.15, curvature=-0.01),
    ]
    for side, sign, outer, lid, ala, corner in (("R", -1, 36, (40, 41), 31, 48),
                                                ("L", +1, 45, (46, 47), 35, 54)):
        out = np.array([sign, 0.0, 0.0])
        sites.append(WrinkleSite(f"crows_feet_{side}", "radial", P[outer] + [sign * 2.0, 0, -2.0],
                                 out, y, (13.0, 8.0), 3.0, 0.8, threshold=0.06, scale=0.15))
        sites.append(WrinkleSite(f"under_eye_{side}", "lines",
                                 snap(P[list(lid)].mean(axis=0) + [0, -9, 0]), x, y,
                                 (10.0, 4.5), 3.5, 0.45, threshold=0.08, scale=0.15,
                                 curvature=-0.012))
        top = P[ala] + [sign * 7.0, 1.0, 0]
        bottom = P[corner] + [sign * 6.0, -6.0, 0]
        along = _unit(bottom - top)
        across = _unit(np.cross(along, [0, 0, 1.0]))
        across = across if across[0] * sign > 0 else -across     # towards the cheek
        sites.append(WrinkleSite(f"nasolabial_{side}", "fold", snap((top + bottom) / 2), along,
                                 across, (0.55 * np.linalg.norm(bottom - top), 9.0), 2.6, 2.0,
                                 threshold=0.08, scale=0.2))
        sites.append(WrinkleSite(f"nose_{side}", "lines", snap(P[29] + [sign * 9.0, 2.0, 0]),
                                 _unit([sign, 1.0, 0]), _unit([-1.0, sign, 0]), (6.0, 4.5),
                                 3.0, 0.5, threshold=0.06, scale=0.15))
    return sites


def _line_strength(index: np.ndarray, salt: int) -> np.ndarray:
    """Deterministic per-line strengths in [0.55, 1] from the line index."""
    h = np.sin((index.astype(np.float64) + 0.37) * (12.9898 + salt) + salt * 78.233) * 43758.5453
    return 0.55 + 0.45 * (h - np.floor(h))


def site_patterns(sites: list[WrinkleSite], P: np.ndarray, N: np.ndarray):
    """Static unit wrinkle patterns of every site at rest points.

    Parameters
    ----------
    P : (k,3) float   rest positions (head frame, mm) — vertices or texel centres
    N : (k,3) float   rest unit normals

    Returns
    -------
    list of (index (j,) int, pattern (j,) float, across (3,j) float) per site: the points
    in the site's support, their unit-amplitude height pattern (furrows negative), and the
    rest tangent direction across the lines at each point (component-major)
    """
    out = []
    for s_i, s in enumerate(sites):
        d = P - s.centre
        xt, xa = d @ s.along, d @ s.across
        if s.kind == "radial":
            r = np.hypot(xt, xa)
            theta = np.arctan2(xa, xt)
            envelope = np.exp(-((r - s.extent[0]) / s.extent[1]) ** 2) * np.exp(-(theta / 0.9) ** 4)
            phase = theta * s.extent[0] / s.wavelength
            across_dir = -np.sin(theta)[:, None] * s.along + np.cos(theta)[:, None] * s.across
        else:
            envelope = np.exp(-(xt / s.extent[0]) ** 2 - (xa / s.extent[1]) ** 2)
            xa_bent = xa + s.curvature * xt ** 2 + 0.8 * np.sin(xt / 9.0 + s_i)
            phase = xa_bent / s.wavelength
            across_dir = np.broadcast_to(s.across, P.shape)
        idx = np.flatnonzero((envelope > 1e-3) & (np.abs(d).max(axis=1) < 80))
        if s.kind == "fold":
            u = phase[idx]
            pattern = -np.exp(-u ** 2) + 0.45 * np.exp(-((u - 1.8) / 1.3) ** 2)
        else:
            k = np.round(phase[idx] + 0.5)
            delta = np.abs(phase[idx] + 0.5 - k)
            furrow = np.exp(-(delta / 0.14) ** 2)
            pattern = (0.25 * (1 - furrow) - furrow) * _line_strength(k, s_i)
        a = across_dir[idx] - np.einsum("ij,ij->i", across_dir[idx], N[idx])[:, None] * N[idx]
        a /= np.maximum(np.linalg.norm(a, axis=1, keepdims=True), 1e-12)
        out.append((idx, pattern * envelope[idx], np.ascontiguousarray(a.T)))
    return out


VOIGT = np.array([0, 4, 8, 1, 2, 5])     # xx yy zz xy xz yz in a flattened 3×3


def quadratic_form(Q: np.ndarray, a: np.ndarray) -> np.ndarray:
    """``aᵀ Q a`` (…,k) for symmetric tensors Q (6,…,k) (Voigt, component-major), a (3,k)."""
    return (Q[0] * a[0] ** 2 + Q[1] * a[1] ** 2 + Q[2] * a[2] ** 2
            + 2 * (Q[3] * a[0] * a[1] + Q[4] * a[0] * a[2] + Q[5] * a[1] * a[2]))


def _det_plus_outer(Q: np.ndarray, n: np.ndarray) -> np.ndarray:
    """``det(Q + n nᵀ)`` (k,) for symmetric Q (6,k) (Voigt, component-major), n (3,k)."""
    xx, yy, zz = Q[0] + n[0] * n[0], Q[1] + n[1] * n[1], Q[2] + n[2] * n[2]
    xy, xz, yz = Q[3] + n[0] * n[1], Q[4] + n[0] * n[2], Q[5] + n[1] * n[2]
    return xx * (yy * zz - yz * yz) - xy * (xy * zz - yz * xz) + xz * (xy * yz - yy * xz)


def area_ratio(Q: np.ndarray, N: np.ndarray, Q_rest: np.ndarray) -> np.ndarray:
    """Local area ratio J (k,) from strain tensors Q, Q_rest (6,k) and rest normals N (3,k).

    Q is (nearly) rank 2 with the rest normal in its kernel, so ``det(Q + N Nᵀ) ≈ J²``;
    dividing by the same at rest makes J exactly 1 there. Clamped to [0.25, 4].
    """
    J2 = _det_plus_outer(Q, N) / np.maximum(_det_plus_outer(Q_rest, N), 1e-12)
    return np.sqrt(np.clip(J2, 1 / 16, 16))


def surface_strain(V0: np.ndarray, V1: np.ndarray, F: np.ndarray) -> np.ndarray:
    """Per-vertex right Cauchy-Green tensors (Voigt order) of the deformation V0 → V1.

    ``Q_i = Σ_t A_t C_t / Σ_t A_t`` over the triangles t around vertex i, with
    ``C_t = F_tᵀF_t`` and ``F_t = E1 E0⁺`` the deformation gradient of triangle t on its
    rest tangent plane (E0, E1 (3,2) rest and deformed edge vectors). Since
    ``F_tᵀF_t = E0⁺ᵀ G E0⁺`` with ``G = E1ᵀE1`` the deformed triangle's first fundamental
    form in the edge basis, C_t is linear in the three entries of G with rest-only
    coefficients, which is how it is computed. For a unit rest tangent a, ``aᵀ Q a`` is the
    squared stretch along a.

    Parameters
    ----------
    V0 : (n,3) float   rest positions
    V1 : (n,3) or (T,n,3) float
    F : (m,3) int

    Returns
    -------
    Q : (n,6) or (T,n,6) float   components xx yy zz xy xz yz (:data:`VOIGT`)
    """
    V0 = np.asarray(V0, dtype=np.float64)
    V1 = np.asarray(V1, dtype=np.float64)
    F = np.asarray(F, dtype=np.int64)
    batched = V1.ndim == 3
    V1 = V1 if batched else V1[None]
    e1, e2 = V0[F[:, 1]] - V0[F[:, 0]], V0[F[:, 2]] - V0[F[:, 0]]
    # rows p1, p2 of E0⁺ = (E0ᵀE0)⁻¹ E0ᵀ
    g11, g22, g12 = (e1 * e1).sum(1), (e2 * e2).sum(1), (e1 * e2).sum(1)
    det = g11 * g22 - g12 ** 2
    p1 = (g22[:, None] * e1 - g12[:, None] * e2) / det[:, None]
    p2 = (g11[:, None] * e2 - g12[:, None] * e1) / det[:, None]

    def voigt_outer(a, b):                      # Voigt components of a bᵀ + b aᵀ, halved
        return np.stack([a[:, 0] * b[:, 0], a[:, 1] * b[:, 1], a[:, 2] * b[:, 2],
                         (a[:, 0] * b[:, 1] + a[:, 1] * b[:, 0]) / 2,
                         (a[:, 0] * b[:, 2] + a[:, 2] * b[:, 0]) / 2,
                         (a[:, 1] * b[:, 2] + a[:, 2] * b[:, 1]) / 2], axis=1)

    area = 0.5 * np.sqrt(det)
    K = np.stack([voigt_outer(p1, p1), voigt_outer(p2, p2), 2 * voigt_outer(p1, p2)], axis=1)
    K *= area[:, None, None]                                       # (m,3,6)
    VF = vertex_face_adjacency(F, len(V0)).astype(np.float64)
    VF = sp.diags(1.0 / (VF @ area)) @ VF                          # area-weighted mean
    T, m = len(V1), len(F)
    Q = np.empty((T, len(V0), 6))
    step = max(1, 400_000 // max(m, 1))
    for s in range(0, T, step):
        E1 = V1[s:s + step, F[:, 1]] - V1[s:s + step, F[:, 0]]
        E2 = V1[s:s + step, F[:, 2]] - V1[s:s + step, F[:, 0]]
        G = np.stack([(E1 * E1).sum(-1), (E2 * E2).sum(-1), (E1 * E2).sum(-1)], axis=-1)
        C = np.einsum("tmk,mkc->mtc", G, K)                        # (m,t,6), area-weighted
        Q[s:s + step] = (VF @ C.reshape(m, -1)).reshape(len(V0), -1, 6).transpose(1, 0, 2)
    return Q if batched else Q[0]


def wrinkle_height(sites, patterns, Q: np.ndarray, Q_rest: np.ndarray,
                   n: int) -> tuple[np.ndarray, np.ndarray]:
    """Wrinkle displacement along the normal at points, for one frame.

    Parameters
    ----------
    patterns : output of :func:`site_patterns` for these points
    Q : (6,n) or (6,T,n) float   strain tensors at the points (Voigt, component-major), in
        one frame or T frames
    Q_rest : (6,n) float         the same at rest
        (the stretch is ``√(aᵀQa / aᵀQ_rest a)``: exactly 1 at rest, where averaging the
        triangles' tangent projectors makes aᵀQ_rest a slightly less than 1)
    n : int             number of points

    Returns
    -------
    height : (n,) or (T,n) float       mm, negative in furrows
    activation : (n,) or (T,n) float   Σ_s (amplitude_s / A_max_s) · envelope_s, in [0, ~1]: how
                              strongly each point is wrinkled (drives fold redness)
    """
    height = np.zeros((*Q.shape[1:-1], n), Q.dtype)
    activation = np.zeros_like(height)
    for s, (idx, pattern, a) in zip(sites, patterns):
        stretch = np.sqrt(np.maximum(quadratic_form(Q[..., idx], a), 0.0)
                          / np.maximum(quadratic_form(Q_rest[:, idx], a), 1e-12))
        amp = s.response(1.0 - stretch)
        height[..., idx] += amp * pattern
        activation[..., idx] += amp / s.amplitude * np.abs(pattern)
    return height, activation


@dataclass(frozen=True)
class PoreField:
    """Static per-texel data of the pore pattern (see :func:`pore_field`).

    offset : (3,k) float     rest-surface vector from the texel to its nearest pore, mm
    depth, radius : (k,) float   the pore's rest depth and radius, mm
    normal : (3,k) float     rest unit normal at the texel (vectors component-major)
    """

    offset: np.ndarray
    depth: np.ndarray
    radius: np.ndarray
    normal: np.ndarray


def pore_field(uv: np.ndarray, J0: np.ndarray, N: np.ndarray, seed: int,
               region_gain: np.ndarray) -> PoreField:
    """Nearest pore of a seeded jittered grid in UV space, for texel centres uv (k,2).

    Each grid cell (PORE_SPACING_UV wide) holds one pore at a hashed jitter, with a hashed
    depth and radius; ``region_gain`` (k,) scales depth (e.g. deeper on nose and cheeks).
    Nearest is measured in the rest metric over the 3×3 neighbouring cells; J0 (k,3,2) is
    the rest Jacobian d(position)/d(uv) of each texel's triangle (mm per uv unit), N (k,3)
    the rest normals.
    """
    cell = np.floor(uv / PORE_SPACING_UV).astype(np.int64)
    best_d2 = np.full(len(uv), np.inf)
    best_off = np.zeros((len(uv), 3))
    best_key = np.zeros(len(uv), dtype=np.int64)
    for di in (-1, 0, 1):
        for dj in (-1, 0, 1):
            c = cell + [di, dj]
            key = c[:, 0] * 1_000_003 + c[:, 1]
            jitter = np.stack([_hash01(key, seed, 1), _hash01(key, seed, 2)], axis=1)
            centre = (c + 0.15 + 0.7 * jitter) * PORE_SPACING_UV
            off = centre - uv
            d3 = np.einsum("kij,kj->ki", J0, off)
            d2 = np.einsum("ki,ki->k", d3, d3)
            closer = d2 < best_d2
            best_d2[closer], best_off[closer], best_key[closer] = d2[closer], d3[closer], key[closer]
    depth = (PORE_DEPTH_MM[0] + (PORE_DEPTH_MM[1] - PORE_DEPTH_MM[0]) * _hash01(best_key, seed, 3) ** 2)
    radius = PORE_RADIUS_MM[0] + (PORE_RADIUS_MM[1] - PORE_RADIUS_MM[0]) * _hash01(best_key, seed, 4)
    return PoreField(np.ascontiguousarray(best_off.T),
                     np.minimum(depth * region_gain, PORE_DEPTH_MM[1]), radius,
                     np.ascontiguousarray(N.T))


def _hash01(key: np.ndarray, seed: int, salt: int) -> np.ndarray:
    """A deterministic hash of integer keys to [0,1) (splitmix64 finaliser)."""
    z = (key.astype(np.uint64) * np.uint64(0x9E3779B97F4A7C15)
         + np.uint64((seed * 0x632BE59BD9B4E019 + salt * 0x85EBCA77C2B2AE63) % 2**64))
    z = (z ^ (z >> np.uint64(30))) * np.uint64(0xBF58476D1CE4E5B9)
    z = (z ^ (z >> np.uint64(27))) * np.uint64(0x94D049BB133111EB)
    z = z ^ (z >> np.uint64(31))
    return (z >> np.uint64(11)).astype(np.float64) / float(2**53)


def pore_height(pores: PoreField, Q: np.ndarray, Q_rest: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Pore displacement (k,) mm at texels, and the area ratio J (k,), for one frame.

    Q, Q_rest (6,k) are the strain tensors at the texels (Voigt, component-major).

    With δ the rest vector to the pore centre, the skin's stretch toward the pore is
    ``λ² = δᵀQδ / δᵀQ_rest δ`` and J its area ratio (:func:`area_ratio`); the pore profile is
    ``−depth · J^-γ · exp(−(|δ| / (radius · λ^β))²)``.
    """
    q0 = np.einsum("ik,ik->k", pores.offset, pores.offset)
    lam = np.sqrt(np.maximum(quadratic_form(Q, pores.offset), 1e-12)
                  / np.maximum(quadratic_form(Q_rest, pores.offset), 1e-12))
    area = area_ratio(Q, pores.normal, Q_rest)
    dist2 = q0 / (pores.radius * lam ** PORE_SHAPE_BETA) ** 2
    return -pores.depth * area ** -PORE_DEPTH_GAMMA * np.exp(-dist2), area


def skin_albedo(base: np.ndarray, area: np.ndarray, activation: np.ndarray,
                pore: np.ndarray | None = None) -> np.ndarray:
    """Linear-RGB albedo (k,3) with blood-flow redness.

    Parameters
    ----------
    base : (k,3) float        static albedo (colour variation, speckle)
    area : (k,) float         local area ratio J (1 at rest)
    activation : (k,) float   wrinkle activation (from :func:`wrinkle_height`)
    pore : (k,) float | None  pore displacement, mm (darkens pore interiors)

    Notes
    -----
    Redness ``ρ = 1.8·max(1−J, 0)^1.2 + 0.35·activation − 0.3·tanh(3·max(J−1, 0))`` is
    absorbed as ``exp(−ρ · REDNESS_ABSORPTION)``: compression and folds redden (pooled
    blood), stretch blanches (bounded: skin cannot get paler than bloodless).
    """
    rho = (1.8 * np.maximum(1 - area, 0) ** 1.2 + 0.35 * activation
           - 0.3 * np.tanh(3 * np.maximum(area - 1, 0)))
    out = base * np.exp(-rho[:, None] * REDNESS_ABSORPTION.astype(base.dtype))
    if pore is not None:
        out = out * (1 + 2.0 * np.clip(pore, -0.2, 0))[:, None]
    return np.clip(out, 0.0, 1.0)


def base_albedo(P: np.ndarray, landmarks: np.ndarray, speckle_key: np.ndarray | None,
                seed: int) -> np.ndarray:
    """Static albedo (k,3) at rest points P: skin base, redder cheeks/nose/lips, speckle.

    landmarks : (68,3) float rest landmark positions; speckle_key (k,) int, texel ids for
    melanin speckle (None at vertices, which cannot carry it).
    """
    def blob(c, s):
        return np.exp(-np.sum((P - c) ** 2, axis=1) / (2 * s * s))

    red = (0.5 * blob(landmarks[2] * 0.5 + landmarks[31] * 0.5, 14.0)
           + 0.5 * blob(landmarks[14] * 0.5 + landmarks[35] * 0.5, 14.0)
           + 0.4 * blob(landmarks[30], 9.0)
           + 0.9 * blob(landmarks[51] * 0.5 + landmarks[57] * 0.5, 9.0))
    out = SKIN_BASE * np.exp(-0.25 * red[:, None] * REDNESS_ABSORPTION)
    if speckle_key is not None:
        speck = _hash01(speckle_key, seed, 9)
        out = out * (1 - 0.06 * speck[:, None] ** 4)
    return out
