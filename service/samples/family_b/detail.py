"""Family b's ground-truth detail: direction-selective creases, elliptic pores, its own albedo.

Everything is driven by the in-plane strain of family b's own high-resolution medium
surface (not the rig's, as family a does), in a smooth local tangent basis:

* **strain**: per triangle t the rest tangent basis (t1, t2) — t2 the projection of the head's
  up axis, t1 = t2 × n — and the 2×2 right Cauchy-Green tensor ``c = [|G t1|², |G t2|²,
  G t1·G t2]`` with G the deformation gradient
  (:func:`~service.geometry.deformation_gradient.deformation_gradients`); area-averaged
  to the vertices and interpolated to texels. Principal stretches ``λ₁ ≥ λ₂``; the
  compression ``κ = 1 − λ₂`` acts along the angle ``ψ`` of the λ₂ eigenvector;
* **creases whose direction follows the compression**: a bank of ``BANKS`` static line
  patterns, bank k with lines perpendicular to the direction ``θ_k = kπ/BANKS`` in the
  head's unwrapped (cylindrical) surface coordinates, wavelength ``λ_k`` in
  WAVELENGTH_MM (2.2–4.0 mm; family a's lines are 3–10 mm); the bank weights
  ``w_k ∝ cos(ψ − θ_k)^(2·SELECTIVITY)`` (normalized) pick the lines perpendicular to the
  compression at each point, so the same skin wrinkles horizontally when squeezed
  vertically and diagonally when squeezed diagonally. Height
  ``A(p) · R(κ) · Σ_k w_k P_k(p)`` with the looseness ``A(p)`` (mm; Gaussians at the
  forehead, glabella, eye corners, lower lids, nasolabial folds, chin and neck, times a smooth
  random factor), the response ``R(κ) = 1 − exp(−(max(κ − κ₀, 0)/κ_s)^1.5)`` (a convex
  onset, family a's is a √ onset) and the **cusp profile** ``P = −e^(−|δ|/δ_c) +
  0.22 (1 − e^(−|δ|/δ_c))`` of the phase distance δ to the nearest crease (sharp V-shaped
  creases between rounded ridges; family a's furrows are Gaussian);
* **pores**: a seeded jittered grid over **3-D rest position** (cells of PORE_CELL_MM, so
  independent of the UV layout), each pore an ellipse (orientation, radii PORE_RADIUS_MM
  and ×PORE_ELONGATION along its axis) with the compact profile ``−d (1 − r²)₊²``; the
  footprint follows the skin only as ``λ^PORE_BETA`` (β = 0.5: pores open slower than the
  skin around them; family a's β is 1.6) and the depth scales as ``J^−1``;
* **albedo**: an olive base with freckles (hashed 3-D cells) and darker lips; compression
  darkens (pigment concentrates, ``× J^0.35``), stretch blanches toward a pale yellow, and
  the creases' floors are darker by up to 25 % (family a reddens with compression).

Shapes: point data component-major, as in the module's functions' docstrings.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

from service.geometry.deformation_gradient import rest_frames_inverse
from service.geometry.normals import face_normals
from service.geometry.topology import vertex_face_adjacency

BANKS = 6
SELECTIVITY = 6
WAVELENGTH_MM = (2.2, 4.0)
CREASE_DECAY = 0.15             # δ_c, in phase units (crease spacing = 1)
RIDGE = 0.22
ONSET, SCALE = 0.03, 0.06       # κ₀, κ_s
LOOSENESS_MM = 1.6
PORE_CELL_MM = 1.7
PORE_RADIUS_MM = (0.28, 0.45)
PORE_ELONGATION = 1.7
PORE_DEPTH_MM = (0.03, 0.12)
PORE_BETA = 0.5
SKIN_BASE = np.array([0.46, 0.33, 0.22])
PALE = np.array([0.72, 0.62, 0.44])
UP = np.array([0.0, 1.0, 0.0])


def tangent_basis(N: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Unit tangents (t1, t2) (k,3) at unit normals N (k,3): t2 = up projected, t1 = t2 × N.

    Where the normal is within ~25° of the up axis (top of the head, under the chin),
    the z axis is projected instead.
    """
    ref = np.where((np.abs(N @ UP) > 0.9)[:, None], np.array([0.0, 0.0, 1.0]), UP)
    t2 = ref - np.einsum("kd,kd->k", ref, N)[:, None] * N
    t2 /= np.linalg.norm(t2, axis=1, keepdims=True)
    return np.cross(t2, N), t2


@dataclass(frozen=True)
class StrainOperator:
    """Precomputed rest data for :meth:`tensors` (per triangle t1, t2 in edge coordinates)."""

    faces: np.ndarray
    coords: np.ndarray          # (m,2,2): t_i = coords[:, i, 0] e1 + coords[:, i, 1] e2 (rest)
    to_vertex: sp.csr_matrix    # (n,m) area-weighted average

    @classmethod
    def build(cls, V0: np.ndarray, F: np.ndarray) -> "StrainOperator":
        F = np.asarray(F, np.int64)
        Ninv = rest_frames_inverse(V0, F)                      # rows map a vector to edge coords
        t1, t2 = tangent_basis(face_normals(V0, F))
        coords = np.stack([np.einsum("mij,mj->mi", Ninv, t)[:, :2] for t in (t1, t2)], axis=1)
        e1, e2 = V0[F[:, 1]] - V0[F[:, 0]], V0[F[:, 2]] - V0[F[:, 0]]
        area = 0.5 * np.linalg.norm(np.cross(e1, e2), axis=1)
        VF = vertex_face_adjacency(F, len(V0)).astype(np.float64) @ sp.diags(area)
        return cls(F, coords, (sp.diags(1.0 / np.asarray(VF.sum(axis=1)).ravel()) @ VF).tocsr())

    def tensors(self, V: np.ndarray) -> np.ndarray:
        """Vertex tensors (3,T,n) ``c11, c22, c12`` for deformed vertices V (T,n,3)."""
        F = self.faces
        E1 = V[:, F[:, 1]] - V[:, F[:, 0]]
        E2 = V[:, F[:, 2]] - V[:, F[:, 0]]
        g = [E1 * self.coords[:, i, 0, None] + E2 * self.coords[:, i, 1, None] for i in (0, 1)]
        c = np.stack([(g[0] * g[0]).sum(-1), (g[1] * g[1]).sum(-1), (g[0] * g[1]).sum(-1)])  # (3,T,m)
        T, m = c.shape[1:]
        out = self.to_vertex @ c.reshape(3 * T, m).T                       # (n,3T)
        return np.ascontiguousarray(out.T.reshape(3, T, -1))


def principal(c: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Principal stretches λ₁ ≥ λ₂ and the angle ψ of the λ₂ direction, for tensors c (3,…)."""
    c11, c22, c12 = c
    mean, half = (c11 + c22) / 2, np.sqrt(((c11 - c22) / 2) ** 2 + c12 ** 2)
    l1, l2 = np.sqrt(np.maximum(mean + half, 0)), np.sqrt(np.maximum(mean - half, 0))
    psi = 0.5 * np.arctan2(2 * c12, c11 - c22) + np.pi / 2     # λ₁ direction + 90°
    return l1, l2, psi


def response(kappa: np.ndarray) -> np.ndarray:
    """R(κ) = 1 − exp(−(max(κ − κ₀, 0)/κ_s)^1.5) in [0,1)."""
    e = np.maximum(kappa - ONSET, 0.0) / SCALE
    return 1.0 - np.exp(-e ** 1.5)


def cusp(phase: np.ndarray) -> np.ndarray:
    """Crease profile of the phase (creases at integers): sharp V floor −1, ridge +RIDGE."""
    delta = np.abs(phase - np.round(phase))
    e = np.exp(-delta / CREASE_DECAY)
    return -e + RIDGE * (1 - e)


def _hash01(key: np.ndarray, seed: int, salt: int) -> np.ndarray:
    """Integer keys → [0,1) (a xorshift-multiply hash on uint64)."""
    z = key.astype(np.uint64) ^ np.uint64((seed * 0xD1B54A32D192ED03 + salt * 0xABC98388FB8FAC03) % 2**64)
    for shift, mult in ((33, 0xFF51AFD7ED558CCD), (33, 0xC4CEB9FE1A85EC53)):
        z = (z ^ (z >> np.uint64(shift))) * np.uint64(mult)
    z = z ^ (z >> np.uint64(33))
    return (z >> np.uint64(11)).astype(np.float64) / float(2**53)


@dataclass(frozen=True)
class Landmarks:
    """Rest landmark positions family b's detail is placed by (all (3,) mm, head frame)."""

    points: np.ndarray          # (68,3) Multi-PIE landmarks on the warped neutral
    axis: np.ndarray            # (3,) a point on the head's vertical axis (x, z)
    radius: float               # unwrap radius, mm


def looseness(P: np.ndarray, lm: Landmarks, seed: int) -> np.ndarray:
    """A(p) (k,) mm: where the skin creases, and how deeply."""
    L = lm.points

    def blob(c, s, w):
        return w * np.exp(-np.sum((P - c) ** 2, axis=1) / (2 * s * s))

    brow = (L[19] + L[24]) / 2
    a = (blob(brow + [0, 26, -4], 22.0, 1.0) + blob((L[21] + L[22]) / 2 + [0, 2, 0], 7.0, 0.8)
         + blob(L[36] + [-7, 0, -5], 8.0, 0.9) + blob(L[45] + [7, 0, -5], 8.0, 0.9)
         + blob(L[40] + [0, -8, 0], 6.0, 0.45) + blob(L[47] + [0, -8, 0], 6.0, 0.45)
         + blob(L[48] + [-6, 8, 0], 9.0, 0.9) + blob(L[54] + [6, 8, 0], 9.0, 0.9)
         + blob(L[8] + [0, 12, 0], 9.0, 0.6) + blob(L[8] + [0, -35, -20], 22.0, 0.5))
    rng = np.random.default_rng([seed, 0xB5])
    k, ph = rng.normal(size=(4, 3)) / 25.0, rng.uniform(0, 2 * np.pi, 4)
    mod = 1.0 + 0.25 * np.sin(P @ k.T + ph).mean(axis=1)
    return LOOSENESS_MM * np.minimum(a, 1.2) * mod


def unwrap(P: np.ndarray, lm: Landmarks) -> tuple[np.ndarray, np.ndarray]:
    """Cylindrical surface coordinates (s, y) (k,) mm: arc length around the head, height."""
    d = P - lm.axis
    return lm.radius * np.arctan2(d[:, 0], d[:, 2]), P[:, 1]


def bank_patterns(P: np.ndarray, lm: Landmarks, seed: int) -> np.ndarray:
    """Static unit crease patterns (BANKS,k) at rest points P (k,3); bank k for compression along θ_k."""
    s, y = unwrap(P, lm)
    rng = np.random.default_rng([seed, 0xB6])
    lam = np.linspace(*WAVELENGTH_MM, BANKS)[rng.permutation(BANKS)]
    out = np.empty((BANKS, len(P)), np.float32)
    for k in range(BANKS):
        th = k * np.pi / BANKS
        along = -np.sin(th) * s + np.cos(th) * y            # coordinate along the lines
        across = np.cos(th) * s + np.sin(th) * y             # across the lines (compression)
        f, ph = rng.uniform(1 / 14, 1 / 8, 2), rng.uniform(0, 2 * np.pi, 3)
        wavy = 0.9 * np.sin(2 * np.pi * f[0] * along + ph[0]) + 0.5 * np.sin(2 * np.pi * f[1] * across + ph[1])
        phase = (across + wavy) / lam[k]
        strength = 0.6 + 0.4 * _hash01(np.floor(phase).astype(np.int64) + 7919 * k, seed, 5)
        fade = 0.75 + 0.25 * np.sin(2 * np.pi * along / 23.0 + ph[2])
        out[k] = cusp(phase) * strength * fade
    return out


def bank_weights(psi: np.ndarray) -> np.ndarray:
    """w_k (BANKS,…) ∝ cos(ψ − θ_k)^(2·SELECTIVITY), normalized to sum 1."""
    th = np.arange(BANKS) * np.pi / BANKS
    w = np.cos(psi[None] - th.reshape((-1,) + (1,) * psi.ndim)) ** (2 * SELECTIVITY)
    return w / w.sum(axis=0, keepdims=True)


def crease_height(c: np.ndarray, patterns: np.ndarray, amplitude: np.ndarray
                  ) -> tuple[np.ndarray, np.ndarray]:
    """Crease height (…,k) mm and activation in [0,1] (…,k) for tensors c (3,…,k).

    patterns (BANKS,k), amplitude A(p) (k,) mm.
    """
    _, l2, psi = principal(c)
    r = response(1.0 - l2)
    w = bank_weights(psi)
    mix = np.einsum("b...k,bk->...k", w, patterns) if c.ndim > 2 else (w * patterns).sum(axis=0)
    return (amplitude * r * mix).astype(np.float32), (r * amplitude / LOOSENESS_MM).astype(np.float32)


@dataclass(frozen=True)
class Pores:
    """Static pore data at texels: tangent offset (2,k) mm to the nearest pore in (t1,t2),
    its axis (2,k) unit, radius across (k,), depth (k,) mm."""

    offset: np.ndarray
    axis: np.ndarray
    radius: np.ndarray
    depth: np.ndarray


def pores(P: np.ndarray, N: np.ndarray, seed: int, gain: np.ndarray) -> Pores:
    """Nearest pore of a jittered 3-D grid for rest points P (k,3), normals N (k,3).

    gain (k,) scales the depth (deeper on the nose and cheeks).
    """
    cell = np.floor(P / PORE_CELL_MM).astype(np.int64)
    best = np.full(len(P), np.inf)
    off = np.zeros((len(P), 3))
    key_best = np.zeros(len(P), np.int64)
    for d in np.stack(np.meshgrid(*[(-1, 0, 1)] * 3, indexing="ij"), -1).reshape(-1, 3):
        c = cell + d
        key = (c[:, 0] * 73856093) ^ (c[:, 1] * 19349663) ^ (c[:, 2] * 83492791)
        centre = (c + 0.1 + 0.8 * np.stack([_hash01(key, seed, j) for j in (1, 2, 3)], 1)) * PORE_CELL_MM
        o = centre - P
        o -= np.einsum("kd,kd->k", o, N)[:, None] * N                     # onto the tangent plane
        d2 = np.einsum("kd,kd->k", o, o) + 4 * (np.einsum("kd,kd->k", centre - P, N)) ** 2
        closer = d2 < best
        best[closer], off[closer], key_best[closer] = d2[closer], o[closer], key[closer]
    t1, t2 = tangent_basis(N)
    ang = np.pi * _hash01(key_best, seed, 4)
    radius = PORE_RADIUS_MM[0] + (PORE_RADIUS_MM[1] - PORE_RADIUS_MM[0]) * _hash01(key_best, seed, 5)
    depth = PORE_DEPTH_MM[0] + (PORE_DEPTH_MM[1] - PORE_DEPTH_MM[0]) * _hash01(key_best, seed, 6)
    f32 = lambda x: np.ascontiguousarray(x, np.float32)
    return Pores(f32(np.stack([np.einsum("kd,kd->k", off, t1), np.einsum("kd,kd->k", off, t2)])),
                 f32(np.stack([np.cos(ang), np.sin(ang)])), f32(radius),
                 f32(np.minimum(depth * gain, PORE_DEPTH_MM[1] * 1.3)))


def area_ratio(c: np.ndarray) -> np.ndarray:
    """J = √det c (…), the local area ratio (rest tensor is the identity), clamped to [0.25, 4]."""
    return np.sqrt(np.clip(c[0] * c[1] - c[2] ** 2, 1 / 16, 16))


def pore_height(p: Pores, c: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Pore displacement (k,) mm and J (k,) for texel tensors c (3,k) of one frame."""
    d = p.offset
    q0 = d[0] ** 2 + d[1] ** 2
    lam2 = (c[0] * d[0] ** 2 + c[1] * d[1] ** 2 + 2 * c[2] * d[0] * d[1]) / np.maximum(q0, 1e-12)
    along = (d[0] * p.axis[0] + d[1] * p.axis[1]) ** 2 / np.maximum(q0, 1e-12)
    inv_r2 = (along / PORE_ELONGATION ** 2 + (1 - along)) / p.radius ** 2
    r2 = q0 * np.maximum(lam2, 1e-6) ** (1 - PORE_BETA) * inv_r2        # distances grow as λ, radius as λ^β
    J = area_ratio(c)
    return (-p.depth / J * np.maximum(1 - r2, 0) ** 2).astype(np.float32), J


def base_albedo(P: np.ndarray, lm: Landmarks, seed: int, freckles: bool) -> np.ndarray:
    """Static albedo (k,3) at rest points: olive base, darker lips, freckles (texels only)."""
    L = lm.points
    lips = np.exp(-np.sum((P - L[48:68].mean(0)) ** 2, axis=1) / (2 * 8.0 ** 2))
    out = SKIN_BASE * (1 - 0.25 * lips[:, None] * np.array([0.2, 0.9, 0.8]))
    if freckles:
        cell = np.floor(P / 2.3).astype(np.int64)
        key = (cell[:, 0] * 73856093) ^ (cell[:, 1] * 19349663) ^ (cell[:, 2] * 83492791)
        cheeks = (np.exp(-np.sum((P - (L[31] + L[2]) / 2) ** 2, 1) / 800.0)
                  + np.exp(-np.sum((P - (L[35] + L[14]) / 2) ** 2, 1) / 800.0) + 0.3)
        spot = (_hash01(key, seed, 8) < 0.12 * cheeks) * _hash01(key, seed, 9)
        out = out * (1 - 0.3 * spot[:, None] * np.array([0.6, 0.8, 1.0]))
    return out


def skin_albedo(base: np.ndarray, J: np.ndarray, activation: np.ndarray, crease: np.ndarray,
                pore: np.ndarray | None = None) -> np.ndarray:
    """Albedo (k,3): compression darkens (× J^0.35), stretch blanches toward PALE, crease floors darker."""
    dark = np.minimum(J, 1.0) ** 0.35
    pale = 0.5 * np.tanh(2.0 * np.maximum(J - 1.0, 0.0))
    out = base * dark[:, None]
    out = out + pale[:, None] * (PALE.astype(base.dtype) - out)
    floor = np.clip(-crease, 0, None) / max(LOOSENESS_MM, 1e-9)
    out = out * (1 - 0.25 * np.clip(floor * activation, 0, 1))[:, None]
    if pore is not None:
        out = out * (1 + 1.5 * np.clip(pore, -0.2, 0))[:, None]
    return np.clip(out, 0.0, 1.0)
