"""One task function per job kind: ``task(job: RunningJob) -> result dict``.

A task reads everything it needs from the store by the ids in ``job.payload``, reports
through ``job.progress`` (where cancellation takes effect) and returns the job's
``result`` (API.md: ``{model_id?, artifact_ids?}``). It raises
:class:`~service.methods.inputs.InvalidInput` for input that cannot be used; the runner
(:mod:`service.jobs.runner`) turns that into the job's error.
"""

from __future__ import annotations

from service.jobs.running import Task
from service.jobs.tasks.bone_rig import BONE_RIG_JOB, bone_rig
from service.jobs.tasks.correspond import correspond_scans
from service.jobs.tasks.register import register
from service.jobs.tasks.synthesize import synthesize
from service.jobs.tasks.track import SPAN_JOB, TRACK_JOB, track, track_span
from service.jobs.tasks.train import train
from service.jobs.tasks.transfer import TRANSFER_JOB, transfer

#: job kind → task function
TASKS: dict[str, Task] = {"train": train, "synthesize": synthesize, "register": register,
                          TRANSFER_JOB: transfer, BONE_RIG_JOB: bone_rig,
                          "correspond": correspond_scans, TRACK_JOB: track,
                          SPAN_JOB: track_span}

__all__ = ["TASKS", "train", "synthesize", "register", "transfer", "bone_rig",
           "correspond_scans", "track", "track_span"]
