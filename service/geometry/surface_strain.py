"""Surface stress per vertex: stretch and compression of the skin relative to the neutral.

Per triangle t the deformation gradient G_t (Sumner & Popović 2004, from
:mod:`service.geometry.deformation_gradient`) maps the neutral triangle onto the frame's;
its right Cauchy–Green tensor ``C_t = G_tᵀ G_t`` is independent of rigid (head) motion.
The triangles' tensors are area-averaged at each vertex, ``C̄_i = Σ A_t C_t / Σ A_t``, and
restricted to the neutral's tangent plane in the vertex's UV frame (T, B): the Green strain

    E_i = ½ ([T B]ᵀ C̄_i [T B] − I)        (2×2; 0 at the neutral)

stored as ``s_i = (E_TT, E_BB, √2 E_TB)`` so that the Euclidean distance of two stress
vectors is the Frobenius distance of the strains. E_TT < 0 is compression along the
texture's u direction (e.g. across horizontal forehead furrows E_BB < 0). Finally the
field is smoothed by ``stress_smoothing`` uniform Laplacian steps: the *local* stress.

This is the "surface stress" of the Digital Ira course's real-time renderer (strain, in
the course's words stress; no material model is involved, so the two differ by the skin's
constant stiffness).
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

from service.geometry.curvature_flow import uniform_smoothing_operator
from service.geometry.deformation_gradient import deformation_gradients, rest_frames_inverse
from service.geometry.laplacian import triangle_areas
from service.geometry.tangent_frames import tangent_frames

#: stress components per vertex (E_TT, E_BB, √2 E_TB)
COMPONENTS = 3
#: :meth:`StressField.operators`' arrays and sparse (CSR) matrices, by field name
OPERATOR_ARRAYS = ("rest_inverse", "tangent")
OPERATOR_MATRICES = ("average", "smoothing")


@dataclass(frozen=True)
class StressField:
    """Everything per-frame stress needs from the neutral, precomputed.

    neutral (n,3), faces (m,3); rest_inverse (m,3,3) Sumner–Popović inverse rest frames;
    average (n,m) area-weighted triangle → vertex averaging; tangent (n,2,3) rest (T, B);
    smoothing (n,n) the smoothing steps as one sparse operator.
    """

    neutral: np.ndarray
    faces: np.ndarray
    rest_inverse: np.ndarray
    average: sp.csr_matrix
    tangent: np.ndarray
    smoothing: sp.csr_matrix

    @classmethod
    def build(cls, neutral: np.ndarray, faces: np.ndarray, uv: np.ndarray, uv_faces: np.ndarray,
              smoothing: int) -> "StressField":
        V = np.asarray(neutral, np.float64)
        F = np.asarray(faces, np.int64)
        n, m = len(V), len(F)
        A = triangle_areas(V, F)
        inc = sp.csr_matrix((np.repeat(A, 3), (F.ravel(), np.repeat(np.arange(m), 3))), shape=(n, m))
        tot = np.asarray(inc.sum(axis=1)).ravel()
        average = (sp.diags(np.where(tot > 0, 1.0 / np.where(tot > 0, tot, 1.0), 0.0)) @ inc).tocsr()
        frames = tangent_frames(V, F, uv, uv_faces)
        S = sp.identity(n, format="csr")
        step = uniform_smoothing_operator(F, n)
        for _ in range(smoothing):
            S = (step @ S).tocsr()
        return cls(V, F, rest_frames_inverse(V, F), average, frames[:, :2], S)

    def operators(self) -> dict:
        """What :meth:`from_operators` takes back (e.g. from a model's cache): ``rest_inverse``
        (m,3,3), ``tangent`` (n,2,3), and the CSR ``average`` and ``smoothing``."""
        return {k: getattr(self, k) for k in OPERATOR_ARRAYS + OPERATOR_MATRICES}

    @classmethod
    def from_operators(cls, neutral: np.ndarray, faces: np.ndarray, operators: dict) -> "StressField | None":
        """The field of the neutral (n,3) and faces (m,3) with the :meth:`operators` stored from
        it (as given: no copy, the strains bit for bit those of the field stored), if all are
        there with the shapes :meth:`build` makes, else None (then build it: ~0.2 s of a
        level-1 PDM load, and the tangent frames' compiled normals loaded)."""
        n, m = len(neutral), len(faces)
        R, T = operators.get("rest_inverse"), operators.get("tangent")
        A, S = operators.get("average"), operators.get("smoothing")
        if not (isinstance(R, np.ndarray) and R.shape == (m, 3, 3) and isinstance(T, np.ndarray)
                and T.shape == (n, 2, 3) and sp.issparse(A) and A.shape == (n, m) and sp.issparse(S)
                and S.shape == (n, n)):
            return None
        return cls(np.asarray(neutral, np.float64), np.asarray(faces, np.int64), R, A.tocsr(), T, S.tocsr())

    def stress32(self, V: np.ndarray) -> np.ndarray:
        """:meth:`stress` of one mesh (n,3) on the compiled kernels
        (:mod:`.strain_kernels`), float32 (n,3): the same formulas summed in another order."""
        from service.geometry import ranges
        from service.geometry.strain_kernels import triangle_metrics, vertex_strain   # Numba

        V = np.ascontiguousarray(V, np.float64)
        C = ranges.scratch("strain.metrics", (len(self.faces), 6), np.float64)
        ranges.run(triangle_metrics, len(self.faces), V, self.faces, self.rest_inverse, C)
        out = np.empty((len(V), COMPONENTS), np.float32)
        a = self.average
        ranges.run(vertex_strain, len(V), a.indptr, a.indices, a.data, C, self.tangent, out)
        if self.smoothed:
            out = (self.smoothing @ out.astype(np.float64)).astype(np.float32)
        return out

    @functools.cached_property
    def smoothed(self) -> bool:
        """Whether ``smoothing`` is more than the identity (``smoothing`` steps > 0)."""
        S = self.smoothing
        return bool((S != sp.identity(S.shape[0], format="csr")).nnz)

    def stress(self, frames: np.ndarray) -> np.ndarray:
        """Local stress (…,n,3) of mesh(es) (…,n,3) in vertex correspondence with the neutral."""
        X = np.asarray(frames, np.float64)
        single = X.ndim == 2
        X = X[None] if single else X
        out = np.empty((len(X), len(self.neutral), COMPONENTS))
        for f, Vf in enumerate(X):
            G = deformation_gradients(self.neutral, Vf, self.faces, self.rest_inverse)
            C = np.einsum("mki,mkj->mij", G, G).reshape(len(G), 9)
            Cv = (self.average @ C).reshape(-1, 3, 3)
            T, B = self.tangent[:, 0], self.tangent[:, 1]
            CT = (Cv @ T[..., None])[..., 0]
            CB = (Cv @ B[..., None])[..., 0]
            ett = 0.5 * (np.sum(T * CT, axis=1) - 1.0)
            ebb = 0.5 * (np.sum(B * CB, axis=1) - 1.0)
            etb = 0.5 * np.sum(T * CB, axis=1)
            out[f] = self.smoothing @ np.column_stack([ett, ebb, np.sqrt(2.0) * etb])
        return out[0] if single else out
