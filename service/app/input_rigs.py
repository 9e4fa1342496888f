"""Input rigs at synthesis time: the ready registration of an actor's rig, found by name,
loaded once per process (checksum verified) and used to carry frames on the rig's topology
to the actor's (bermano2014 §5.1, :meth:`RigRegistration.propagate`).

``/enhance``, ``/retime`` and synthesis jobs take ``rig=<name>``; :func:`load_rig` answers
with a :class:`LoadedRig` or raises by meaning: ``NotFound`` (no rig of that name: 404),
``Conflict`` (still registering, with its job; registration failed, with the reason; or
registered to a neutral of another vertex count: 409).
"""

from __future__ import annotations

from dataclasses import dataclass
import numpy as np
from sqlalchemy.orm import Session

from models_store import registry
from models_store.errors import Conflict, NotFound
from models_store.schema import InputRig
from service.app.services import Services
from service.app.synthesis import Expected
from service.methods.shape_space.registration import RigRegistration

#: the job kind that registers an input rig (:mod:`service.jobs.tasks.register`)
REGISTER_JOB = "register"


@dataclass(frozen=True)
class LoadedRig:
    """A ready input rig and its loaded registration.

    Attributes
    ----------
    rig_id : str             the rig's id
    name : str               its name (the ``{rig}`` of the API path)
    blob, sha256 : str       the registration blob's key and digest (what a job records)
    registration : RigRegistration   the (n,v) propagation operator (v rig, n actor vertices)
    """

    rig_id: str
    name: str
    blob: str
    sha256: str
    registration: RigRegistration

    @property
    def vertex_count(self) -> int:
        """v, the rig's vertices per frame."""
        return self.registration.n_rig_vertices

    def expected(self, model: Expected) -> Expected:
        """What a request's frames must be for ``model`` when given on this rig:
        ``vertices`` (F,v,3)."""
        return Expected(model.model_id, model.kind, "vertices", self.vertex_count,
                        owner=f"input rig {self.name!r}")

    def propagate(self, frames: np.ndarray) -> np.ndarray:
        """Frames (F,v,3) on the rig's topology → (F,n,3) float64 on the actor's."""
        return self.registration.propagate(frames)

    def payload(self) -> dict[str, str]:
        """The job payload entries that pin this registration (a job propagates its frames
        with exactly these bytes, or fails if the rig was uploaded again meanwhile)."""
        return {"rig_id": self.rig_id, "rig": self.name, "registration_blob": self.blob,
                "registration_sha256": self.sha256}


def ready_rig(session: Session, actor_id: str, name: str) -> InputRig:
    """The actor's input rig ``name`` if its registration is ready.

    Raises
    ------
    NotFound   the actor has no rig of that name (the message lists the ones it has)
    Conflict   the rig is still registering (naming its registration job) or its
               registration failed (with the reason)
    """
    try:
        rig = registry.get_input_rig(session, actor_id, name)
    except NotFound as error:
        if error.kind != "input rig":
            raise
        names = [r.name for r in registry.list_input_rigs(session, actor_id)]
        raise NotFound("input rig", name, (
            f"actor {actor_id!r} has " + (f"the input rigs {', '.join(names)}" if names else
                                          "no input rigs") +
            f"; upload one with PUT /v1/actors/{actor_id}/input-rigs/{name}")) from None
    if rig.status == "registering":
        jobs = [job for job in registry.list_jobs(session, actor_id=actor_id, kind=REGISTER_JOB)
                if job.status in ("queued", "running") and job.payload.get("rig_id") == rig.id]
        where = (f" (job {jobs[-1].id} is {jobs[-1].status}; follow it at "
                 f"/v1/jobs/{jobs[-1].id})" if jobs else "")
        raise Conflict(f"input rig {name!r} is still registering{where}; it can be used once "
                       "its registration succeeds")
    if rig.status == "failed":
        error = rig.error or {}
        raise Conflict(f"input rig {name!r} failed to register ({error.get('code', 'error')}: "
                       f"{error.get('message', 'no reason recorded')}); upload it again with "
                       f"PUT /v1/actors/{actor_id}/input-rigs/{name}")
    return rig


def _nbytes(registration: RigRegistration) -> int:
    """Memory held by a registration, bytes."""
    P = registration.operator
    return int(P.data.nbytes + P.indices.nbytes + P.indptr.nbytes
               + registration.rig_neutral.nbytes + registration.neutral.nbytes)


def load_rig(services: Services, actor_id: str, name: str, n_vertices: int | None) -> LoadedRig:
    """The ready input rig ``name`` of an actor with its registration, from the process's
    cache (keyed by rig id and registration sha256) or the blob store (verified).

    Parameters
    ----------
    actor_id : str
    name : str                the rig's name
    n_vertices : int or None  the model's vertex count n; a registration onto a neutral of
                              another count is a Conflict

    Raises
    ------
    NotFound, Conflict   as :func:`ready_rig`; Conflict too if the rig was uploaded again
                         while its registration was being read
    """
    with services.session() as session:
        rig = ready_rig(session, actor_id, name)
        rig_id, blob, sha256 = rig.id, rig.registration_blob, rig.registration_sha256

    def load() -> RigRegistration:
        try:
            return RigRegistration.load(services.blobs.read_bytes(blob, sha256))
        except NotFound:
            raise Conflict(f"input rig {name!r} was uploaded again while its registration "
                           "was being read; retry once the new registration succeeds") from None

    registration = services.registrations.get_or_load((rig_id, sha256), load, _nbytes)
    if n_vertices is not None and registration.n_vertices != n_vertices:
        raise Conflict(f"input rig {name!r} was registered to a neutral of "
                       f"{registration.n_vertices} vertices; the model has {n_vertices}. Upload "
                       "the rig again to register it to the current neutral")
    return LoadedRig(rig_id, name, blob, sha256, registration)

