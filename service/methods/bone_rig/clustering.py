"""Initialization of the bone rig by clustering (after Le & Deng 2012 §4, "initialization").

1. k-means (k-means++ seeding, seeded) on vertex trajectories: the rest position and the
   positions in ``cluster_frames`` evenly spaced frames, so that vertices that move
   together start in one cluster;
2. per cluster, the rigid transform of every frame that best maps its rest vertices onto
   the frame (Kabsch, :func:`~service.geometry.rigid.rigid_align_frames`);
3. rigid-bone iterations: every vertex goes to the one bone that alone reproduces it best
   over all frames, the bones are refitted, ``init_iterations`` times (the special case
   K = 1 of the SSDR alternation, which starts the smooth solve from a rigid rig).

Clusters that end up empty are dropped (the rig has fewer bones; py-dem-bones does the
same). Departure: SSDR's own initialization grows clusters from one bone by splitting;
trajectory k-means is simpler to vectorize and lands in the same kind of rigid rig.
"""

from __future__ import annotations

import numpy as np

from service.geometry.rigid import rigid_align_frames
from service.methods.bone_rig.transforms import MIN_BONE_VERTICES
from service.methods.bone_rig.weights import (
    CHUNK, frame_sums, homogeneous, right_hand_sides, single_bone_errors, vertex_major,
)


def rigid_fit(rest: np.ndarray, frames_vm: np.ndarray, labels: np.ndarray,
              bones: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Rigid transforms (F,B,3,3), (F,B,3) of every cluster, and which bones are usable (B,),
    for the vertex-major frames (V, F·3)."""
    F = frames_vm.shape[1] // 3
    R = np.broadcast_to(np.eye(3), (F, bones, 3, 3)).copy()
    t = np.zeros((F, bones, 3))
    ok = np.zeros(bones, bool)
    for j in range(bones):
        v = np.flatnonzero(labels == j)
        if len(v) < MIN_BONE_VERTICES:
            continue
        try:
            Ri, ti = rigid_align_frames(frames_vm[v].reshape(len(v), F, 3).transpose(1, 0, 2), rest[v])
        except ValueError:
            continue
        R[:, j] = np.swapaxes(Ri, 1, 2)
        t[:, j] = -np.einsum("fij,fj->fi", R[:, j], ti)
        ok[j] = True
    return R, t, ok


def assign(rest: np.ndarray, frames_vm: np.ndarray, R: np.ndarray, t: np.ndarray,
           usable: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Each vertex's best single bone (V,) and that bone's error Σ_t ‖·‖² (V,), mm², for
    the vertex-major frames (V, F·3)."""
    ph = homogeneous(rest)
    M, G = frame_sums(R, t)
    labels = np.empty(len(rest), np.int64)
    best = np.empty(len(rest))
    for s in range(0, len(rest), CHUNK):
        sl = slice(s, min(s + CHUNK, len(rest)))
        err = single_bone_errors(ph[sl], G, right_hand_sides(frames_vm, M, sl))
        err[:, ~usable] = np.inf
        labels[sl] = np.argmin(err, axis=1)
        best[sl] = err[np.arange(len(err)), labels[sl]] + np.einsum("vd,vd->v", frames_vm[sl], frames_vm[sl])
    return labels, np.maximum(best, 0.0)


def kmeans_pp(X: np.ndarray, k: int, rng: np.random.Generator) -> np.ndarray:
    """k-means++ seeds (k,D) of points X (V,D) (Arthur & Vassilvitskii 2007), keeping the
    running nearest-seed distance (O(V·D·k))."""
    seeds = np.empty((k, X.shape[1]))
    seeds[0] = X[rng.integers(len(X))]
    d2 = np.sum((X - seeds[0]) ** 2, axis=1)
    for i in range(1, k):
        tot = d2.sum()
        j = rng.choice(len(X), p=d2 / tot) if tot > 0 else rng.integers(len(X))
        seeds[i] = X[j]
        d2 = np.minimum(d2, np.sum((X - seeds[i]) ** 2, axis=1))
    return seeds


def initial_rig(rest: np.ndarray, frames: np.ndarray, bones: int, cluster_frames: int,
                init_iterations: int, seed: int, frames_vm: np.ndarray | None = None,
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Rigid rig to start SSDR from (module docstring).

    Returns
    -------
    labels : (V,) int    bone of each vertex, in [0, B') with B' ≤ bones the bones kept
    R : (F,B',3,3), t : (F,B',3)
    """
    F, V = len(frames), len(rest)
    bones = min(bones, V)
    frames_vm = vertex_major(frames) if frames_vm is None else frames_vm
    pick = np.unique(np.round(np.linspace(0, F - 1, min(cluster_frames, F))).astype(np.int64))
    feats = np.concatenate([rest[:, None], frames[pick].transpose(1, 0, 2)], axis=1).reshape(V, -1)
    if bones == 1:
        labels = np.zeros(V, np.int64)
    else:
        from scipy.cluster.vq import kmeans2  # imported here: serve's start never needs it (issue 23's cold start)

        rng = np.random.default_rng(seed)
        _, labels = kmeans2(feats, kmeans_pp(feats, bones, rng), minit="matrix", missing="warn")
    R, t, ok = rigid_fit(rest, frames_vm, labels, bones)
    for _ in range(init_iterations):
        new, _ = assign(rest, frames_vm, R, t, ok)
        if np.array_equal(new, labels):
            break
        labels = new
        R, t, ok = rigid_fit(rest, frames_vm, labels, bones)
    keep = np.flatnonzero(ok & (np.bincount(labels, minlength=bones) >= MIN_BONE_VERTICES))
    if not len(keep):
        raise ValueError("no bone has enough vertices")
    if len(keep) < bones or not ok[labels].all():
        labels, _ = assign(rest, frames_vm, R, t, np.isin(np.arange(bones), keep))
    remap = np.full(bones, -1)
    remap[keep] = np.arange(len(keep))
    return remap[labels], R[:, keep], t[:, keep]
