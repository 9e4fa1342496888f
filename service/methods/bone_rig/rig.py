"""A solved bone rig: rest mesh, sparse weights, per-frame bone transforms; NPZ and glTF.

NPZ layout (``save_npz``): ``rest`` (V,3) float32 mm, ``faces`` (m,3) int32 (absent when
unknown), ``joints`` (V,K) uint16 and ``weights`` (V,K) float32 (rows sum to 1, zeros in
unused slots), ``rotations`` (F,B,3,3) float32 and ``translations`` (F,B,3) float32 (rest →
frame, ``v = Σ w (R p + t)``), ``joint_rest`` (B,3) float32 the joints' rest positions
(the centroid of each bone's vertices, weighted), ``fps``.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from service.io.atomic import write_npz
from service.methods.bone_rig.skinning import skin


@dataclass
class BoneRig:
    """Linear-blend-skinning rig.

    Attributes
    ----------
    rest : (V,3) float64          rest pose, mm
    faces : (m,3) int or None
    index : (V,K) int64           bone of each influence, by decreasing weight
    weight : (V,K) float64        non-negative, rows sum to 1
    R : (F,B,3,3) float64         bone rotations rest → frame
    t : (F,B,3) float64           bone translations, mm
    fps : float
    metrics : dict
    """

    rest: np.ndarray
    faces: np.ndarray | None
    index: np.ndarray
    weight: np.ndarray
    R: np.ndarray
    t: np.ndarray
    fps: float = 30.0
    metrics: dict = field(default_factory=dict)

    @property
    def bones(self) -> int:
        return int(self.R.shape[1])

    @property
    def frames(self) -> int:
        return int(self.R.shape[0])

    def reconstruct(self) -> np.ndarray:
        """The skinned animation (F,V,3) float64."""
        return skin(self.rest, self.index, self.weight, self.R, self.t)

    def joint_rest(self) -> np.ndarray:
        """Rest positions (B,3) of the joints: the weighted centroid of each bone's vertices
        (the origin of a bone that drives none)."""
        W = np.zeros((len(self.rest), self.bones))
        np.add.at(W, (np.repeat(np.arange(len(self.rest)), self.index.shape[1]), self.index.ravel()),
                  self.weight.ravel())
        mass = W.sum(axis=0)
        c = (W.T @ self.rest) / np.where(mass > 0, mass, 1.0)[:, None]
        c[mass <= 0] = 0.0
        return c

    def save_npz(self, path) -> str:
        """Write the rig as NPZ (module docstring); returns the file's sha256."""
        arrays = {"rest": self.rest.astype(np.float32), "joints": self.index.astype(np.uint16),
                  "weights": self.weight.astype(np.float32),
                  "rotations": self.R.astype(np.float32), "translations": self.t.astype(np.float32),
                  "joint_rest": self.joint_rest().astype(np.float32), "fps": np.float32(self.fps)}
        if self.faces is not None:
            arrays["faces"] = self.faces.astype(np.int32)
        return write_npz(path, arrays)

    @classmethod
    def load_npz(cls, path) -> "BoneRig":
        """Read a rig written by :meth:`save_npz`."""
        with np.load(Path(path)) as d:
            return cls(d["rest"].astype(np.float64),
                       d["faces"].astype(np.int64) if "faces" in d.files else None,
                       d["joints"].astype(np.int64), d["weights"].astype(np.float64),
                       d["rotations"].astype(np.float64), d["translations"].astype(np.float64),
                       float(d["fps"]))

    def write_glb(self, path) -> str:
        """Write the rig as a binary glTF 2.0 skin with its animation
        (:func:`service.io.gltf.write_skinned_glb`); returns the file's sha256."""
        from service.io.gltf import write_skinned_glb

        return write_skinned_glb(path, self.rest, self.faces, self.index, self.weight,
                                 self.R, self.t, self.joint_rest(), self.fps)

    def write_usd(self, path) -> None:
        """Write the rig as a UsdSkel stage (skeleton, animation, skinned mesh;
        :func:`service.io.usd_skel.write_skinned_usd`)."""
        from service.io.usd_skel import write_skinned_usd

        write_skinned_usd(path, self.rest, self.faces, self.index, self.weight,
                          self.R, self.t, self.joint_rest(), self.fps)
