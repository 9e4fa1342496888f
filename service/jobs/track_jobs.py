"""The job kinds of tracking (fyffe, digital_ira_course2014 §4–5.7) and the query of a
``track`` job's children, for the job (:mod:`service.jobs.tasks.track`) and the operation
that queues and cancels it (:mod:`service.app.tracking`) without that importing the task's
methods (issue 23: ``facesynth serve``'s imports before its first frame).
"""

from __future__ import annotations

from sqlalchemy.orm import Session

from models_store import registry
from models_store.schema import Job
from service.jobs.running import RunningJob

#: the parent job: graph, keyframes, maps (one per tracking upload)
TRACK_JOB = "track"
#: a child job: the in-between frames of one span between keyframes
SPAN_JOB = "track_span"


def span_jobs(session: Session, job: Job | RunningJob) -> list[Job]:
    """The ``track_span`` jobs a ``track`` job created, oldest first."""
    return [j for j in registry.list_jobs(session, kind=SPAN_JOB, actor_id=job.actor_id)
            if (j.payload or {}).get("parent_job_id") == job.id]
