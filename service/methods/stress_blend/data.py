"""What a trained stress-blend model stores: :class:`StressBlendData`, round-tripped by
:mod:`.store`; what synthesis precomputes from it is the
:class:`~service.methods.stress_blend.model.StressBlendEvaluator`."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from service.methods.stress_blend.params import StressBlendParams


@dataclass(frozen=True)
class StressBlendData:
    """What a trained stress-blend model stores (:mod:`.store` round-trips it).

    Arrays: neutral (n,3) mm, faces (m,3), uv (K,2), uv_faces (m,3); scan_stress (S,n,3)
    float64 (scan 0 the neutral); displacement (S,H,H) float32 and albedo (S,Ha,Ha,3) or
    None, the scans' maps; masks (n,R) the wrinkle regions; importance (K,n) per-expression
    map change at the vertices; scan_names (S,) e.g. "train_smile:9".
    """

    params: StressBlendParams
    neutral: np.ndarray
    faces: np.ndarray
    uv: np.ndarray
    uv_faces: np.ndarray
    scan_names: list
    scan_stress: np.ndarray
    displacement: np.ndarray
    albedo: np.ndarray | None
    masks: np.ndarray
    importance: np.ndarray
    metrics: dict = field(default_factory=dict)

    @property
    def n_vertices(self) -> int:
        return len(self.neutral)

    @property
    def n_scans(self) -> int:
        return len(self.scan_stress)


__all__ = ["StressBlendData"]
