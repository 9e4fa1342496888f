"""One task function per job kind: ``task(job: RunningJob) -> result dict``.

A task reads everything it needs from the store by the ids in ``job.payload``, reports
through ``job.progress`` (where cancellation takes effect) and returns the job's
``result`` (API.md: ``{model_id?, artifact_ids?}``). It raises
:class:`~service.methods.inputs.InvalidInput` for input that cannot be used; the runner
(:mod:`service.jobs.runner`) turns that into the job's error.

:data:`TASKS` (job kind → task function) imports the task modules when it is first read
(PEP 562 module ``__getattr__``), so importing one task module for its job kind's name
(``service.app.tracking``, ``service.app.bone_rigs``, ``service.app.transfer``) does not
import every method the other tasks run (issue 23: the USD writer, the bone-rig
decomposition, … on ``facesynth serve``'s path to its first frame).
"""

from __future__ import annotations

from typing import Any

from service.jobs.running import Task


def _tasks() -> dict[str, Task]:
    """Job kind → task function (the runner's table)."""
    from service.jobs.tasks.bone_rig import BONE_RIG_JOB, bone_rig
    from service.jobs.tasks.correspond import correspond_scans
    from service.jobs.tasks.register import register
    from service.jobs.tasks.synthesize import synthesize
    from service.jobs.tasks.track import track, track_span
    from service.jobs.tasks.train import train
    from service.jobs.tasks.transfer import TRANSFER_JOB, transfer
    from service.jobs.track_jobs import SPAN_JOB, TRACK_JOB

    return {"train": train, "synthesize": synthesize, "register": register,
            TRANSFER_JOB: transfer, BONE_RIG_JOB: bone_rig, "correspond": correspond_scans,
            TRACK_JOB: track, SPAN_JOB: track_span}


def __getattr__(name: str) -> Any:
    if name == "TASKS":   # built once, then an ordinary module attribute
        table = globals()["TASKS"] = _tasks()
        return table
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


__all__ = ["TASKS"]
