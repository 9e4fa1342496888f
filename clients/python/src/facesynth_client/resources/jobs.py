"""``client.jobs``: job state, progress events, waiting, cancellation, artifacts (``/v1/jobs``)."""

from __future__ import annotations

from typing import Any

from .._core import Call, job_id_of
from ..types import Artifact, Job
from ._base import Resource

__all__ = ["Jobs"]


class Jobs(Resource):
    """``/v1/jobs``: state, progress events, cancellation, artifacts."""

    def get(self, job: Any) -> Job:
        """A job's state (``job``: an id, a :class:`Job` or an accepted job)."""
        return self._run(self._core.get_job(job_id_of(job)))

    def list(self, *, status: str | None = None, actor_id: str | None = None,
             kind: str | None = None, model_id: str | None = None) -> list[Job]:
        """Jobs, oldest first, filtered by any of ``status``, ``actor_id``, ``kind``,
        ``model_id``."""
        params = {"status": status, "actor_id": actor_id, "kind": kind, "model_id": model_id}
        return self._run(self._core.call_items(Call("GET", "/v1/jobs", params=params),
                                               Job.from_json))

    def cancel(self, job: Any) -> Job:
        """Cancel a job: a queued one is ``cancelled`` at once, a running one stops at its
        next progress point (the returned state may still say ``running``); a finished one
        is returned unchanged."""
        return self._run(self._core.call_json(Call("DELETE", f"/v1/jobs/{job_id_of(job)}"),
                                              Job.from_json))

    def artifacts(self, job: Any) -> list[Artifact]:
        """The downloadable results of a job."""
        return self._run(self._core.call_items(
            Call("GET", f"/v1/jobs/{job_id_of(job)}/artifacts"), Artifact.from_json))

    def events(self, job: Any) -> Any:
        """The job's states from its event stream (``GET /v1/jobs/{id}/events``) until it
        ends: an iterator of :class:`Job` (an async iterator on :class:`AsyncClient`).

        Examples
        --------
        >>> for state in client.jobs.events(job_id):                         # doctest: +SKIP
        ...     print(f"{state.progress:.0%} {state.stage}")
        """
        return self._client._iterate(self._core.follow_events(job_id_of(job), None))

    def wait(self, job: Any, timeout: float | None = None, progress: Any = False, *,
             poll_interval: float | None = None, events: bool = True) -> Job:
        """Wait until a job ends.

        Follows the job's event stream (``GET /v1/jobs/{id}/events``); if the stream
        cannot be opened or breaks, polls ``GET /v1/jobs/{id}`` every ``poll_interval``
        seconds instead.

        Parameters
        ----------
        job : str, Job, ModelAccepted, RigAccepted or JobAccepted
        timeout : float, optional   seconds; None waits as long as it takes
        progress : bool or callable
            True: a text progress bar on stderr (tqdm's if it is installed); a callable
            ``(job) -> None`` is called with every new state
        poll_interval : float, optional   seconds between polls (default: the client's)
        events : bool   False: poll only

        Returns
        -------
        Job   the succeeded job (``.result.model_id``, ``.artifact_ids``)

        Raises
        ------
        JobFailed      the job failed (``.code``, ``.message``, ``.job``)
        JobCancelled   the job was cancelled
        WaitTimeout    ``timeout`` passed first (the job goes on)

        Examples
        --------
        >>> job = client.jobs.wait(client.models.train(actor_id, "pdm", clip_ids),
        ...                        timeout=3600, progress=True)           # doctest: +SKIP
        >>> client.jobs.wait(job_id, progress=lambda j: print(j.progress, j.stage))  # doctest: +SKIP
        """
        return self._run(self._core.wait(job, timeout, progress, poll_interval, events))
