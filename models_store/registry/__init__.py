"""The operations the API and the jobs call: actors, clips, input rigs, models, jobs, artifacts.

Import the package and call its functions (``from models_store import registry``;
``registry.create_actor(session, "Ada")``); the submodules hold one resource each:
:mod:`.actors` (with the neutral and the marker layout), :mod:`.clips`, :mod:`.rigs`, :mod:`.scans`,
:mod:`.models`, :mod:`.jobs`, :mod:`.artifacts`.

Each operation is a plain function over a SQLAlchemy ``Session`` (from
:func:`models_store.db.make_session_factory`) and, where blobs are involved, a
:class:`~models_store.blobs.BlobStore`. Each is one unit of work: it commits before
returning, and returns the ORM rows it made or changed (still readable after the commit).
Failures raise :class:`~models_store.errors.NotFound` (unknown or malformed id) or
:class:`~models_store.errors.Conflict` (the state forbids it); a malformed argument that only
a programming error could produce raises ``ValueError``.

Blobs and rows are kept consistent without a distributed transaction: a new blob is written
(under a fresh, never reused key) before the row that references it is committed, and
deleted again if that commit fails; an old blob is deleted only after the commit that stops
referencing it. A crash can therefore leave an unreferenced blob behind, never a row pointing
to a missing or half-written blob.

Tenants: actors, models and jobs have a tenant; clips and rigs are their actor's, artifacts
their job's. Every lookup and listing is limited to :data:`TENANT_SCOPE`, which a request
sets for its duration with :func:`acting_for` (unset — jobs, maintenance, admins — it is
every tenant); another tenant's id raises the same ``NotFound`` as an unknown one.

Jobs: every state change is one conditional UPDATE, so concurrent API processes, workers and
reapers cannot both win a transition::

    queued ──claim──▶ running ──finish──▶ succeeded | failed | cancelled
      ▲                 │ lease expired (reap_expired): requeued while attempts <= max_retries,
      └─────────────────┘ then failed with code "lease_expired"

A worker holds a running job through a lease (``worker``, ``lease_expires_at``) that it
renews with :func:`heartbeat` (or :func:`update_job_progress` with ``lease_seconds``);
calls naming a ``worker`` that no longer holds the job raise ``Conflict`` ("lease lost"), so
a worker that was presumed dead stops instead of overwriting its successor's work.
Cancellation is cooperative: :func:`request_cancel` cancels a queued job at once and flags a
running one, which sees ``cancel_requested`` at its next progress point and finishes as
``cancelled``. A training job that ends failed or cancelled marks its model failed, so no
model stays ``training`` forever. Lease expiry compares wall clocks: the machines of a
deployment must keep their clocks synchronized (NTP) to well within the lease.
"""

from models_store.registry._common import TENANT_OWNER, TENANT_SCOPE, acting_for
from models_store.registry.actors import (create_actor, delete_actor, get_actor, list_actors,
                                          read_markers, read_neutral, set_markers, set_neutral)
from models_store.registry.artifacts import (add_artifact, get_artifact, list_artifacts,
                                             open_artifact)
from models_store.registry.clips import add_clip, delete_clip, get_clip, list_clips, read_clip
from models_store.registry.jobs import (MAX_CLAIM_ROUNDS, Reaped, claim_job, create_job,
                                        finish_job, get_job, heartbeat, list_jobs, park_job,
                                        reap_expired,
                                        request_cancel, update_job_progress)
from models_store.registry.models import (create_model, delete_model, get_model, list_models,
                                          mark_model_failed, mark_model_ready, model_dir)
from models_store.registry.rigs import (get_input_rig, get_input_rig_by_id, list_input_rigs, mark_rig_failed,
                                        mark_rig_ready, put_input_rig)
from models_store.registry.scans import add_scan, delete_scan, get_scan, list_scans, read_scan

__all__ = [
    # tenants
    "acting_for", "TENANT_SCOPE", "TENANT_OWNER",
    # actors
    "create_actor", "get_actor", "list_actors", "delete_actor", "set_neutral", "set_markers",
    "read_neutral", "read_markers",
    # clips
    "add_clip", "get_clip", "list_clips", "read_clip", "delete_clip",
    # input rigs
    "put_input_rig", "get_input_rig", "get_input_rig_by_id", "list_input_rigs", "mark_rig_ready", "mark_rig_failed",
    # scans
    "add_scan", "get_scan", "list_scans", "read_scan", "delete_scan",
    # models
    "create_model", "get_model", "list_models", "mark_model_ready", "mark_model_failed",
    "model_dir", "delete_model",
    # jobs
    "create_job", "get_job", "list_jobs", "update_job_progress", "heartbeat", "request_cancel",
    "park_job",
    "claim_job", "finish_job", "reap_expired", "Reaped", "MAX_CLAIM_ROUNDS",
    # artifacts
    "add_artifact", "get_artifact", "list_artifacts", "open_artifact",
]
