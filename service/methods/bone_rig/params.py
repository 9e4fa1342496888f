"""Parameters of the bone-rig decomposition (one frozen pydantic model)."""

from __future__ import annotations

from pydantic import Field

from service.methods.params import MethodParams


class BoneRigParams(MethodParams):
    """Parameters of :func:`service.methods.bone_rig.decomposition.decompose` (Le & Deng 2012).

    The course's game rig had 70 bones on a 4K-polygon mesh; glTF engines and most game
    runtimes skin with at most 4 (some 8) influences per vertex.
    """


    bones: int = Field(
        default=70, ge=1, le=1024,
        description="Number of bones B (SSDR §3; the course's rig used 70). Bones that end "
                    "up driving no vertex are dropped, so the rig may have fewer.")
    max_influences: int = Field(
        default=4, ge=1, le=8,
        description="Largest number of non-zero weights per vertex |w_i|_0 <= K (SSDR eq. 4; "
                    "glTF's JOINTS_0/WEIGHTS_0 hold 4, JOINTS_1/WEIGHTS_1 the next 4).")
    iterations: int = Field(
        default=30, ge=0, le=500,
        description="Alternations of the bone-transform update (§3.2) and the weight update "
                    "(§3.3) after the initialization.")
    init_iterations: int = Field(
        default=10, ge=0, le=200,
        description="Rigid-bone iterations of the initialization (§4.1): assign every vertex "
                    "to the one bone that best predicts it, refit the bones.")
    candidates: int = Field(
        default=8, ge=1, le=64,
        description="Bones considered per vertex in the weight update: the vertex's current "
                    "bones and those that predict it best alone (at least max_influences).")
    qp_iterations: int = Field(
        default=20, ge=1, le=5000,
        description="Accelerated projected-gradient steps that start the per-vertex simplex "
                    "QP of the weight update (an active-set method then solves it exactly).")
    cluster_frames: int = Field(
        default=24, ge=1, le=1000,
        description="Frames (evenly spaced) whose positions form the trajectory features of "
                    "the k-means clustering that seeds the bones.")
    seed: int = Field(default=0, description="Seed of the k-means initialization.")
