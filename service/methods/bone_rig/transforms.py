"""The bone update of SSDR (Le & Deng 2012 §3): each bone's rigid transform per frame by
weighted Procrustes, with the weights and the other bones fixed.

For bone j and frame t, with the residual of the other bones
``q_i = v_i^t − Σ_{k≠j} w_ik (R_k^t p_i + T_k^t)``,

    Σ_i ‖q_i − w_ij (R p_i + T)‖² = Σ_i w_ij² ‖R p_i + T − q_i / w_ij‖²

over the vertices the bone influences, a weighted rigid alignment of the rest points onto
the targets ``q_i / w_ij`` with weights ``w_ij²`` (the closed form of the paper's bone
update), solved for all frames at once by :func:`~service.geometry.rigid.rigid_align_frames`.
Bones are updated one after the other (block coordinate descent), each seeing the others'
latest transforms, so the objective never rises.
"""

from __future__ import annotations

import numpy as np

from service.geometry.rigid import rigid_align_frames

#: fewest influenced vertices a bone needs for its rotation to be determined
MIN_BONE_VERTICES = 3


def update_transforms(rest: np.ndarray, frames_vm: np.ndarray, index: np.ndarray,
                      weight: np.ndarray, R: np.ndarray, t: np.ndarray,
                      recon_vm: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Refit every bone's transforms (module docstring); ``recon_vm`` is updated in place.

    Parameters
    ----------
    rest : (V,3);  frames_vm : (V,F,3) the animation, vertex-major (rows gather fast), mm
    index, weight : (V,K) the influences
    R : (F,B,3,3), t : (F,B,3)   current transforms (not modified)
    recon_vm : (V,F,3)   the current skinned result (:func:`~.skinning.skin`, vertex-major);
                         on return it holds the skinned result of the new transforms

    Returns
    -------
    R, t : the new transforms. A bone with fewer than :data:`MIN_BONE_VERTICES` influenced
    vertices keeps its transforms.
    """
    R, t = R.copy(), t.copy()
    B = R.shape[1]
    used = weight > 0
    for j in range(B):
        sel = used & (index == j)
        v = np.flatnonzero(sel.any(axis=1))
        if len(v) < MIN_BONE_VERTICES:
            continue
        w = (weight * sel)[v].sum(axis=1)                              # (n,)
        p = rest[v]
        own = w[:, None, None] * (np.matmul(R[:, j], p.T).transpose(2, 0, 1) + t[None, :, j])
        q = frames_vm[v] - recon_vm[v] + own                            # (n,F,3)
        try:
            Ri, ti = rigid_align_frames((q / w[:, None, None]).transpose(1, 0, 2), p, w * w)   # targets → rest
        except ValueError:
            continue
        Rn = np.swapaxes(Ri, 1, 2)                                      # rest → targets
        tn = -np.einsum("fij,fj->fi", Rn, ti)
        if not (np.isfinite(Rn).all() and np.isfinite(tn).all()):
            continue
        R[:, j], t[:, j] = Rn, tn
        recon_vm[v] += w[:, None, None] * (np.matmul(Rn, p.T).transpose(2, 0, 1) + tn[None]) - own
    return R, t
