"""Smooth Skinning Decomposition with Rigid Bones (Le & Deng 2012, ACM TOG 31(6) 199).

Given an animation (F frames × V vertices) and a rest pose, finds sparse convex weights
and per-frame rigid bone transforms minimizing the reconstruction error of linear blend
skinning (their §3):

    min Σ_t Σ_i ‖v_i^t − Σ_j w_ij (R_j^t p_i + T_j^t)‖²
    s.t. w_ij ≥ 0,  Σ_j w_ij = 1,  |{j : w_ij ≠ 0}| ≤ K,  R_j^tᵀ R_j^t = I,  det R_j^t = 1

by alternating the bone update (:mod:`.transforms`, weighted Procrustes per bone) and the
weight update (:mod:`.weights`, a constrained least-squares problem per vertex), from the
rigid rig of :mod:`.clustering`. Each update solves its block exactly (bones) or to
convergence from the previous iterate (weights), so the error does not rise; the loop
stops after ``iterations`` or when the RMS improves by less than ``RELATIVE_TOLERANCE``.

This is the "Game Rig" step of the Digital Ira course (2014): the performance was
"transferred ... to standard bone animation ... using a bone weight and transform solver"
(70 bones on the game mesh).
"""

from __future__ import annotations

import time

import numpy as np

from service.methods.bone_rig.clustering import initial_rig
from service.methods.bone_rig.params import BoneRigParams
from service.methods.bone_rig.rig import BoneRig
from service.methods.bone_rig.skinning import skin
from service.methods.bone_rig.transforms import update_transforms
from service.methods.bone_rig.weights import update_weights, vertex_major
from service.methods.inputs import InvalidInput, Progress, no_progress

#: stop when an alternation lowers the RMS error by less than this fraction
RELATIVE_TOLERANCE = 1e-4


def check_animation(frames, rest=None, faces=None) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """Validated float64 copies of an animation (F,V,3), its rest pose (V,3) and faces.

    Raises :class:`InvalidInput` for empty arrays, wrong shapes, non-finite frames (naming
    the first), a rest pose of another vertex count, or faces out of range.
    """
    A = np.asarray(frames, dtype=np.float64)
    if A.ndim != 3 or A.shape[2] != 3:
        raise InvalidInput(f"the animation must be (frames, vertices, 3), got shape {A.shape}")
    if A.shape[0] == 0 or A.shape[1] == 0:
        raise InvalidInput(f"the animation is empty: {A.shape[0]} frames of {A.shape[1]} vertices "
                           "(at least 1 frame of 3 vertices is needed)")
    if A.shape[1] < 3:
        raise InvalidInput(f"the animation has {A.shape[1]} vertices; at least 3 are needed")
    bad = np.flatnonzero(~np.isfinite(A).all(axis=(1, 2)))
    if len(bad):
        v = np.flatnonzero(~np.isfinite(A[bad[0]]).all(axis=1))
        raise InvalidInput(f"frame {bad[0]} has non-finite vertices (first: vertex {v[0]}); "
                           f"{len(bad)} of {len(A)} frames are affected")
    P = A[0].copy() if rest is None else np.asarray(rest, dtype=np.float64)
    if P.shape != A.shape[1:]:
        raise InvalidInput(f"the rest pose must be ({A.shape[1]},3) like the frames, got {P.shape}")
    if not np.isfinite(P).all():
        raise InvalidInput("the rest pose has non-finite vertices")
    Fc = None
    if faces is not None:
        Fc = np.asarray(faces, dtype=np.int64)
        if Fc.ndim != 2 or Fc.shape[1] != 3 or (len(Fc) and (Fc.min() < 0 or Fc.max() >= A.shape[1])):
            raise InvalidInput(f"faces must be (m,3) vertex indices in [0, {A.shape[1]}), got "
                               f"shape {Fc.shape}")
    return A, P, Fc


def rms(recon: np.ndarray, frames: np.ndarray) -> float:
    """RMS vertex error (mm) of a reconstruction."""
    return float(np.sqrt(np.mean(np.sum((recon - frames) ** 2, axis=-1))))


def decompose(frames: np.ndarray, rest: np.ndarray | None = None, faces: np.ndarray | None = None,
              params: BoneRigParams = BoneRigParams(), fps: float = 30.0,
              progress: Progress = no_progress) -> BoneRig:
    """A linear-blend-skinned bone rig reproducing an animation (module docstring).

    Parameters
    ----------
    frames : (F,V,3) float   the animation, mm (world space; head motion is carried by the bones)
    rest : (V,3) float       rest pose (default: frame 0)
    faces : (m,3) int        triangles (exported with the rig; not needed by the solve)
    params : BoneRigParams
    fps : float              frame rate of the exported animation

    Returns
    -------
    BoneRig   with ``metrics``: rms_mm and max_mm of the reconstruction, rms per iteration,
              bones kept, seconds

    Raises
    ------
    InvalidInput   empty or mis-shaped arrays, non-finite frames, a bone count above V
    """
    A, P, Fc = check_animation(frames, rest, faces)
    if params.bones > A.shape[1]:
        raise InvalidInput(f"bones = {params.bones} exceeds the vertex count {A.shape[1]}")
    if not (np.isfinite(fps) and fps > 0):
        raise InvalidInput(f"fps must be positive, got {fps}")
    t0 = time.perf_counter()
    progress(0.0, "initialization")
    A_vm = vertex_major(A)
    labels, R, t = initial_rig(P, A, params.bones, params.cluster_frames, params.init_iterations,
                               params.seed, A_vm)
    index = labels[:, None].astype(np.int64)
    weight = np.ones((len(P), 1))
    A_v = A_vm.reshape(len(P), -1, 3)                                  # (V,F,3) view
    recon = skin(P, index, weight, R, t).transpose(1, 0, 2)            # (V,F,3) contiguous
    history = [rms(recon, A_v)]
    progress(0.1, "alternation")
    for it in range(params.iterations):
        R, t = update_transforms(P, A_v, index, weight, R, t, recon)
        index, weight = update_weights(P, A_vm, R, t, index, weight, params.max_influences,
                                       params.candidates, params.qp_iterations)
        recon = skin(P, index, weight, R, t).transpose(1, 0, 2)
        history.append(rms(recon, A_v))
        progress(0.1 + 0.9 * (it + 1) / params.iterations, "alternation")
        if history[-2] - history[-1] <= RELATIVE_TOLERANCE * history[-2]:
            break
    err = np.linalg.norm(recon - A_v, axis=-1)
    K = params.max_influences
    if index.shape[1] < K:                       # pad to K slots (iterations = 0)
        pad = K - index.shape[1]
        index = np.pad(index, ((0, 0), (0, pad)))
        weight = np.pad(weight, ((0, 0), (0, pad)))
    metrics = {"rms_mm": history[-1], "max_mm": float(err.max()), "rms_history_mm": history,
               "bones": int(R.shape[1]), "bones_requested": params.bones,
               "iterations": len(history) - 1, "seconds": time.perf_counter() - t0,
               "params": params.model_dump()}
    progress(1.0, "done")
    return BoneRig(P, Fc, index.astype(np.int64), weight, R, t, float(fps), metrics)
