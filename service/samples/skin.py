"""The sample actor's high-resolution skin: a new identity of the ICT rig, Loop-subdivided.

Level 0 is the rig itself (11,248 vertices), level 1 one Loop pass (44,786 vertices),
level 2 two passes (178,726). Subdivision is a fixed sparse operator ``S``, so every
rig pose maps to the high-resolution surface as ``S @ pose`` and the rig's vertices keep
indices ``[0, 11248)``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

from service.geometry.subdivision import subdivide
from service.samples.rig import IctRig
from service.samples.uv_layout import repack_ict_uv

MAX_LEVEL = 2


@dataclass(frozen=True)
class Skin:
    """High-resolution skin of one identity.

    Attributes
    ----------
    rig_neutral : (n0,3) float     the identity's neutral at rig resolution, mm
    rig_uv : (K0,2) float          the rig's UVs repacked into [0,1]² (rig.triangle_uv indexes them)
    neutral : (n,3) float          high-resolution neutral, mm
    faces : (m,3) int              high-resolution triangles
    uv : (K,2) float               UVs in [0,1]² (API.md convention)
    uv_faces : (m,3) int           per-corner UV indices
    S : (n,n0) sparse              rig → high-resolution operator
    region : (n,) int              rig region of each vertex (0 narrow face, 1 face, 2 head)
    level : int
    """

    rig_neutral: np.ndarray
    neutral: np.ndarray
    faces: np.ndarray
    uv: np.ndarray
    uv_faces: np.ndarray
    S: sp.csr_matrix
    region: np.ndarray
    level: int
    rig_uv: np.ndarray


    def upsample(self, rig_values: np.ndarray) -> np.ndarray:
        """High-resolution values (n,C) or (T,n,C) of rig-resolution ones (n0,C) or (T,n0,C)."""
        X = np.asarray(rig_values, dtype=np.float64)
        if X.ndim == 2:
            return self.S @ X
        T, n0, C = X.shape
        flat = X.transpose(1, 0, 2).reshape(n0, T * C)
        return (self.S @ flat).reshape(-1, T, C).transpose(1, 0, 2)


def identity_coefficients(seed: int, count: int = 10, clip: float = 2.0) -> np.ndarray:
    """Seeded identity coefficients c_k ~ N(0,1), clipped to ±clip std. deviations."""
    rng = np.random.default_rng([seed, 0x1D])
    return np.clip(rng.standard_normal(count), -clip, clip)


def build_skin(rig: IctRig, identity: np.ndarray, level: int) -> Skin:
    """Subdivide the identity ``level`` times and repack its UVs into [0,1]².

    Parameters
    ----------
    identity : (≤10,) float   identity coefficients (see :func:`identity_coefficients`)
    level : 0, 1 or 2
    """
    if not 0 <= level <= MAX_LEVEL:
        raise ValueError(f"level must be 0, 1 or 2, got {level}")
    rig_neutral = rig.identity(identity)
    uv01 = repack_ict_uv(rig.uv, rig.triangle_uv)
    sub = subdivide(rig.triangles, rig.n_vertices, rig.triangle_uv, len(rig.uv),
                    iterations=level, scheme="loop")
    # a new vertex belongs to the highest-numbered region among its stencil's vertices
    support = sub.S.tocoo()
    region = np.zeros(sub.S.shape[0], dtype=np.int64)
    np.maximum.at(region, support.row, rig.region[support.col])
    return Skin(
        rig_neutral=rig_neutral,
        neutral=sub.S @ rig_neutral,
        faces=sub.faces,
        uv=sub.S_uv @ uv01,
        uv_faces=sub.uv_faces,
        S=sub.S,
        region=region,
        level=level,
        rig_uv=uv01,
    )
