"""Family b's identity and skin: extreme rig identities, a smooth random warp, its own mesh and UVs.

* **identity**: the ICT rig's 10 identity modes with coefficients of magnitude 2.4–3.4
  standard deviations (family a clips at ±2), signs seeded;
* **warp**: every rig pose (neutral *and* expressions) is mapped through one smooth,
  seeded space warp ``φ(x) = A x + Σ_j a_j exp(−|x − c_j|² / 2 s_j²)`` — an anisotropic
  scale A (face width, height, depth each ×0.9–1.1) plus 12 Gaussian bumps (σ 22–40 mm,
  |a| ≤ 5 mm, so ‖∇‖ ≲ 0.15 and φ stays a diffeomorphism). Expressions are warped with the
  face (``φ(neutral + Δ)``), so blendshapes change shape, not only the neutral;
* **mesh**: :mod:`service.samples.family_b.mesh` (other diagonals, red-green refinement,
  butterfly, spatial vertex order). Level 0: the narrow face within ZONE_RADIUS_MM of the
  eyes and the mouth refined once; level 1: the whole narrow face once, then those zones
  again (vertex counts: see the tests);
* **UVs** in [0,1]²: the rig's face chart is cut along the facial midline (a seam family a
  does not have) and each half rotated a quarter turn, the right half stacked above the
  left in [0,0.8]×[0.2,1]; the neck chart is turned upright into the right strip
  [0.8,1]×[0.2,1]; head and ears share the bottom strip [0,1]×[0,0.2].
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import connected_components

from service.geometry.topology import adjacency_matrix
from service.samples.family_b import mesh as fmesh
from service.samples.rig import IctRig

IDENTITY_RANGE = (2.4, 3.4)
WARP_BUMPS = 12
WARP_SIGMA_MM = (22.0, 40.0)
WARP_AMPLITUDE_MM = 5.0
WARP_SCALE = (0.9, 1.1)
GUTTER = 0.01
MAX_LEVEL = 1
ZONE_RADIUS_MM = 30.0           # around the eyes and the mouth: refined once more


@dataclass(frozen=True)
class Warp:
    """The smooth space warp φ (see module docstring): A (3,3), centres (J,3), sigma (J,), amplitude (J,3)."""

    A: np.ndarray
    centres: np.ndarray
    sigma: np.ndarray
    amplitude: np.ndarray

    def __call__(self, X: np.ndarray) -> np.ndarray:
        """φ(X) for points X (…,3), mm."""
        X = np.asarray(X, np.float64)
        d2 = ((X[..., None, :] - self.centres) ** 2).sum(-1)          # (…,J)
        return X @ self.A.T + np.exp(-d2 / (2 * self.sigma ** 2)) @ self.amplitude


def identity_coefficients(seed: int) -> np.ndarray:
    """10 coefficients of magnitude in IDENTITY_RANGE with seeded signs."""
    rng = np.random.default_rng([seed, 0xB1])
    return rng.choice([-1.0, 1.0], size=10) * rng.uniform(*IDENTITY_RANGE, size=10)


def make_warp(seed: int, surface: np.ndarray) -> Warp:
    """A seeded warp whose bump centres lie on the front of ``surface`` (n,3)."""
    rng = np.random.default_rng([seed, 0xB2])
    front = surface[surface[:, 2] > np.percentile(surface[:, 2], 40)]
    centres = front[rng.choice(len(front), WARP_BUMPS, replace=False)]
    amp = rng.standard_normal((WARP_BUMPS, 3))
    amp *= WARP_AMPLITUDE_MM * rng.uniform(0.4, 1.0, (WARP_BUMPS, 1)) / np.linalg.norm(amp, axis=1, keepdims=True)
    return Warp(np.diag(rng.uniform(*WARP_SCALE, 3)), centres,
                rng.uniform(*WARP_SIGMA_MM, WARP_BUMPS), amp)


@dataclass(frozen=True)
class Skin:
    """Family b's high-resolution skin of one identity.

    Attributes
    ----------
    rig_neutral : (n0,3)  warped identity at rig resolution, mm (the low-resolution input rig)
    rig_uv : (K0,2)       the rig's own UVs repacked into [0,1]² for input_rig.npz
    neutral : (n,3)       high-resolution neutral, mm
    faces, uv_faces : (m,3) int;  uv : (K,2) in [0,1]²
    S : (n,n0) sparse     rig pose → high-resolution positions
    region : (n,) int     0 narrow face, 1 rest of the face, 2 head & neck
    warp : Warp;  identity : (10,)
    """

    rig_neutral: np.ndarray
    rig_uv: np.ndarray
    neutral: np.ndarray
    faces: np.ndarray
    uv: np.ndarray
    uv_faces: np.ndarray
    S: sp.csr_matrix
    region: np.ndarray
    warp: Warp
    identity: np.ndarray

    def pose(self, rig: IctRig, weights: np.ndarray) -> np.ndarray:
        """Warped rig poses (T,n0,3) for blendshape weights (T,53): φ(identity + Σ w Δ)."""
        raw = rig.identity(self.identity) + rig.expression_offsets(weights)
        return self.warp(raw)

    def upsample(self, rig_values: np.ndarray) -> np.ndarray:
        """High-resolution values (T,n,C) of rig-resolution ones (T,n0,C)."""
        X = np.asarray(rig_values, np.float64)
        T, n0, C = X.shape
        return (self.S @ X.transpose(1, 0, 2).reshape(n0, T * C)).reshape(-1, T, C).transpose(1, 0, 2)


def _rotate_fit(uv: np.ndarray, quarter_turns: int, box) -> np.ndarray:
    """Rotate points (k,2) by quarter turns about their centre, then fit uniformly into box."""
    c = (uv.min(0) + uv.max(0)) / 2
    R = np.array([[0.0, -1.0], [1.0, 0.0]])
    p = (uv - c) @ np.linalg.matrix_power(R, quarter_turns % 4).T
    lo, hi = p.min(0), p.max(0)
    u0, v0, u1, v1 = box[0] + GUTTER, box[1] + GUTTER, box[2] - GUTTER, box[3] - GUTTER
    s = min((u1 - u0) / (hi[0] - lo[0]), (v1 - v0) / (hi[1] - lo[1]))
    return (p - (lo + hi) / 2) * s + np.array([(u0 + u1) / 2, (v0 + v1) / 2])


def family_b_uv(rig: IctRig) -> tuple[np.ndarray, np.ndarray]:
    """Family b's UV layout of the rig's triangles (module docstring).

    Returns
    -------
    uv : (K,2) float in [0,1]²;  uv_faces : (m,3) int indexing it, one row per rig triangle
    """
    uv0, UF = np.asarray(rig.uv, np.float64), np.asarray(rig.triangle_uv, np.int64)
    K0 = len(uv0)
    # decided per quad (triangle pair), so the cut runs along quad edges
    quad_x = np.repeat(rig.neutral[rig.triangles].mean(axis=1)[:, 0].reshape(-1, 2).mean(axis=1), 2)
    face_tile = uv0[UF].mean(axis=1)[:, 0] < 1.0
    right = face_tile & (quad_x < 0)              # the actor's right half of the face chart
    UF = UF.copy()
    UF[right] += K0                               # its own copies of the UV vertices
    uv = np.concatenate([uv0, uv0])
    used, UF = np.unique(UF, return_inverse=True)
    UF = UF.reshape(-1, 3)
    uv = uv[used]
    _, chart = connected_components(adjacency_matrix(UF, len(uv)), directed=False)
    out = np.empty_like(uv)
    corner_right = np.zeros(len(uv), bool)
    corner_right[UF[right].ravel()] = True
    corner_left = np.zeros(len(uv), bool)
    corner_left[UF[face_tile & ~right].ravel()] = True
    head = ~(corner_right | corner_left)
    out[corner_right] = _rotate_fit(uv[corner_right], 1, (0.0, 0.6, 0.8, 1.0))
    out[corner_left] = _rotate_fit(uv[corner_left], -1, (0.0, 0.2, 0.8, 0.6))
    charts = np.unique(chart[head])
    lowest = {c: uv[chart == c, 1].min() for c in charts}
    neck = head & (chart == min(lowest, key=lowest.get))
    rest = head & ~neck
    out[neck] = _rotate_fit(uv[neck], 1, (0.8, 0.2, 1.0, 1.0))
    out[rest] = _rotate_fit(uv[rest], 0, (0.0, 0.0, 1.0, 0.2))
    return out, UF


def build_skin(rig: IctRig, seed: int, level: int) -> Skin:
    """Identity, warp, refined and reordered mesh, UVs (module docstring); level 0 or 1."""
    if not 0 <= level <= MAX_LEVEL:
        raise ValueError(f"family b has levels 0 and 1, got {level}")
    identity = identity_coefficients(seed)
    raw = rig.identity(identity)
    warp = make_warp(seed, raw)
    rig_neutral = warp(raw)
    F0 = fmesh.flip_quad_diagonals(rig.triangles)
    uv, UF0 = family_b_uv(rig)
    UF0 = fmesh.flip_quad_diagonals(UF0)
    n0 = rig.n_vertices
    lm = rig_neutral[rig.landmarks68]
    zones = np.stack([lm[36:42].mean(0), lm[42:48].mean(0), lm[48:68].mean(0)])

    def near_zones(m_: fmesh.RefinedMesh) -> np.ndarray:
        c = (m_.S @ rig_neutral)[m_.faces].mean(axis=1)
        d = np.linalg.norm(c[:, None] - zones, axis=2).min(axis=1)
        return (d < ZONE_RADIUS_MM) & (m_.region[m_.faces] == 0).all(axis=1)

    m = fmesh.RefinedMesh(sp.identity(n0, format="csr"), F0, sp.identity(len(uv), format="csr"),
                          UF0, np.asarray(rig.region, np.int64))
    passes = [near_zones] if level == 0 else [lambda m_: (m_.region[m_.faces] == 0).all(axis=1), near_zones]
    for mark in passes:
        m = fmesh.compose(m, fmesh.refine(m.faces, m.S.shape[0], m.uv_faces, m.S_uv.shape[0],
                                          m.region, mark(m)))
    V = m.S @ rig_neutral
    m = fmesh.reorder(m, fmesh.spatial_order(V))
    return Skin(rig_neutral, _rig_uv(rig), m.S @ rig_neutral, m.faces, m.S_uv @ uv, m.uv_faces,
                m.S, m.region, warp, identity)


def _rig_uv(rig: IctRig) -> np.ndarray:
    """The rig's UV vertices fitted into [0,1]² as two side-by-side tiles (input rig only)."""
    uv = np.asarray(rig.uv, np.float64)
    return (uv - uv.min(0)) / (uv.max(0) - uv.min(0)).max() * (1 - 2 * GUTTER) + GUTTER
