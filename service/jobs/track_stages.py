"""The stages of a ``track`` job and the share of its progress each takes, declared once for
the job (:mod:`service.jobs.tasks.track`) and the clients that draw a bar per stage
(``facesynth track``). fyffe, digital_ira_course2014 §4–5.7: the candidate flows of the
performance flow graph, the voting, the full-resolution flows of the retained edges, the
keyframe solve, the in-between spans (one child job each), then the per-frame scan
weights and blended maps (§7.3) and storing the artifacts.
"""

from __future__ import annotations

#: stage name → (start, end) of the job's progress, in order
STAGES: dict[str, tuple[float, float]] = {
    "graph flows": (0.0, 0.25),
    "graph selection": (0.25, 0.3),
    "full flows": (0.3, 0.45),
    "keyframe solve": (0.45, 0.6),
    "tween solve": (0.6, 0.85),
    "maps": (0.85, 0.97),
    "storing results": (0.97, 1.0),
}


def overall(stage: str, fraction: float) -> float:
    """The job's progress at ``fraction`` ∈ [0,1] of ``stage``."""
    start, end = STAGES[stage]
    return start + (end - start) * min(max(float(fraction), 0.0), 1.0)


def within(stage: str, progress: float) -> float:
    """The fraction of ``stage`` done at the job's progress ``progress`` (0 for a stage
    this table does not name)."""
    if stage not in STAGES:
        return 0.0
    start, end = STAGES[stage]
    return min(max((float(progress) - start) / (end - start), 0.0), 1.0)
