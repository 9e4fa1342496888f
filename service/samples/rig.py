"""The ICT face rig (MIT, ICT-FaceKit "Face Model Light", skin only), as shipped in data/.

A linear morphable model in millimetres: ``neutral + Σ c_k identity_deltas[k] +
Σ w_j expression_deltas[j]``; see ``data/README.md`` for the keys and their provenance.
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path

import numpy as np

RIG_PATH = Path(__file__).with_name("data") / "ict_face_rig.npz"
RIG_SHA256 = "606172e965b8dc3b85c92eccbace87b29f436ade729366db56bed12813bae174"


@dataclass(frozen=True)
class IctRig:
    """The rig's arrays (float64 positions in mm; n = 11248 vertices).

    Attributes
    ----------
    neutral : (n,3)                 generic neutral
    triangles, triangle_uv : (m,3)  each quad (a,b,c,d) split as (a,b,c), (a,c,d)
    uv : (K,2)                      two UDIM tiles: face u∈[0,1), head & neck u∈[1,2)
    expression_names : (53,) str    ARKit-style blendshape names
    expression_deltas : (53,n,3)    blendshape − neutral
    identity_deltas : (10,n,3)      PCA identity modes scaled by their std. deviation
    landmarks68 : (68,) int         Multi-PIE landmarks (vertex ids)
    rigid_vertices : (r,) int       skull-attached vertices
    region : (n,) int               0 narrow face, 1 rest of the face, 2 head & neck
    """

    neutral: np.ndarray
    triangles: np.ndarray
    triangle_uv: np.ndarray
    uv: np.ndarray
    expression_names: tuple[str, ...]
    expression_deltas: np.ndarray
    identity_deltas: np.ndarray
    landmarks68: np.ndarray
    rigid_vertices: np.ndarray
    region: np.ndarray

    @property
    def n_vertices(self) -> int:
        return len(self.neutral)

    def expression_index(self, name: str) -> int:
        """Index of a blendshape by its ARKit name (``KeyError`` naming the valid ones)."""
        try:
            return self.expression_names.index(name)
        except ValueError:
            raise KeyError(f"unknown blendshape {name!r}; the rig has {', '.join(self.expression_names)}") from None

    def identity(self, coefficients: np.ndarray) -> np.ndarray:
        """Neutral (n,3) of the identity ``neutral + Σ c_k identity_deltas[k]``, c (≤10,)."""
        c = np.asarray(coefficients, dtype=np.float64)
        return self.neutral + np.tensordot(c, self.identity_deltas[: len(c)], axes=1)

    def expression_offsets(self, weights: np.ndarray) -> np.ndarray:
        """Blendshape offsets (F,n,3) for weights (F,53) (or (n,3) for one (53,) vector)."""
        w = np.asarray(weights, dtype=np.float64)
        flat = w.reshape(-1, w.shape[-1]) @ self.expression_deltas.reshape(len(self.expression_names), -1)
        return flat.reshape(w.shape[:-1] + (self.n_vertices, 3))


@lru_cache(maxsize=2)
def load_ict_rig(path: str | Path = RIG_PATH) -> IctRig:
    """Load and checksum-verify the rig (cached; arrays are read-only)."""
    raw = Path(path).read_bytes()
    digest = hashlib.sha256(raw).hexdigest()
    if Path(path) == RIG_PATH and digest != RIG_SHA256:
        raise ValueError(f"{path} is corrupt: sha256 {digest}, expected {RIG_SHA256}")
    with np.load(path, allow_pickle=False) as d:
        arrays = {k: d[k] for k in d.files}

    def ro(a, dtype):
        a = np.ascontiguousarray(a, dtype=dtype)
        a.setflags(write=False)
        return a

    return IctRig(
        neutral=ro(arrays["neutral"], np.float64),
        triangles=ro(arrays["triangles"], np.int64),
        triangle_uv=ro(arrays["triangle_uv"], np.int64),
        uv=ro(arrays["uv"], np.float64),
        expression_names=tuple(str(s) for s in arrays["expression_names"]),
        expression_deltas=ro(arrays["expression_deltas"], np.float64),
        identity_deltas=ro(arrays["identity_deltas"], np.float64),
        landmarks68=ro(arrays["landmarks68"], np.int64),
        rigid_vertices=ro(arrays["rigid_vertices"], np.int64),
        region=ro(arrays["region"], np.int64),
    )
