"""What the API (and the gRPC server beside it) share for the life of a process.

:class:`Services` opens the metadata database (migrating it to the current schema), the blob
store and the byte-budgeted cache of loaded models; :meth:`Services.load_model` is the one
way to get a ready model, used by the HTTP routes and, as ``load_model``, by the gRPC
server (:func:`service.grpc.server.serve`), so both share one cache. Both also synthesize in
one pool of ``max_concurrent_syntheses`` slots (:attr:`Services.synthesis`,
:class:`~service.app.threads.SynthesisPool`), the count the BLAS threads are sized against.
"""

from __future__ import annotations

import contextlib
import json
import logging
import threading
import time
from dataclasses import dataclass, field
from typing import Any, Callable, Sequence

import numpy as np
from sqlalchemy import Engine, text
from sqlalchemy.orm import Session

from models_store import registry
from models_store.blobs import BlobStore
from models_store.cache import ByteLRUCache
from models_store.registry._common import in_tenant
from service.app.limits import REGISTRATION_CACHE_BYTES
from service.app.marker_units import MarkerReference, face_unit, layout_positions
from service.app.memory import release_free_heap
from service.app.threads import SynthesisPool, cores
from service.config import Settings
from service.methods.footprint import nbytes
from service.errors import Conflict
from service.jobs.job_threads import JobThreads
from service.jobs.queue_storage import probe as probe_queue
from service.methods.kinds import Kind, get_kind, takes
from service.store.actors import neutral_arrays
from service.store.container import Store, get_store

log = logging.getLogger("facesynth.api")

#: hands a queued job (by id) to the task queue
Submit = Callable[[str], None]

#: seconds for which one read of a ready model's row answers for it (issue 23: the row read,
#: the actor read of the marker check and their two sessions were 0.4 ms of a quiet
#: level-1 mesh request and 4 ms of one under load 6, against a 4 ms budget). A ready
#: model's row is immutable until it is deleted (its status, tenant, actor, kind and files;
#: its actor's neutral and marker layout cannot change while the actor has models:
#: ``registry.set_neutral`` / ``set_markers``), so the only staleness is of a deletion: one
#: made in this process drops the model at once (:meth:`Services.forget_model`); one made
#: by another process (another server worker, the CLI) answers 404 here within this time.
#: The tenant check is made on every request against the row's (immutable) tenant.
READY_RECHECK_SECONDS = 1.0
#: most ready rows remembered (the oldest read is dropped first)
READY_ROWS = 1024


@dataclass(frozen=True)
class ReadyRow:
    """What one read of a ready model's row established (:data:`READY_RECHECK_SECONDS`).

    Attributes
    ----------
    id, tenant, kind, actor_id : the row's (immutable while the model exists)
    size_bytes : int     its files' size
    checked : float      ``time.monotonic()`` of the read
    """

    id: str
    tenant: str
    kind: str
    actor_id: str | None
    size_bytes: int
    checked: float


@dataclass
class LoadedModel:
    """A ready model in memory with what the routes need to know about it.

    Attributes
    ----------
    id : str          model id
    kind : Kind       its kind (``kind.input`` says whether it takes markers or meshes)
    model : object    the loaded model (``synthesize(frames, outputs, clamp) -> dict``)
    actor_id : str    the actor it was trained for (whose input rigs and clips it can use)
    stream : object   what the gRPC server synthesizes with: the model, or for marker-driven
                      kinds a :class:`UnitCheckedModel` of it
    topology : Topology or None   the topology resource (``service.app.operations``), cached
    reference : MarkerReference or None   the actor's marker layout on its neutral when the
                      model was loaded (:meth:`Services.marker_reference`; it cannot change
                      while the model exists), for the unit check of marker frames
    """

    id: str
    kind: Kind
    model: Any
    actor_id: str | None = None
    stream: Any = None
    #: the model's topology resource (NPZ body, ETag), built on its first request
    topology: Any = None
    reference: MarkerReference | None = None


@dataclass(frozen=True)
class UnitCheckedModel:
    """A marker-driven model whose ``synthesize`` first refuses marker frames in another
    unit than the actor's layout (:mod:`service.app.marker_units`, a 422 / INVALID_ARGUMENT
    naming the likely unit); every other attribute is the model's."""

    model: Any
    reference: MarkerReference | None

    def synthesize(self, markers: np.ndarray, outputs: Any = ("mesh", "displacement"),
                   clamp: bool = True, **options: Any) -> dict[str, np.ndarray]:
        frames = np.asarray(markers, np.float64)
        frames = frames[None] if frames.ndim == 2 else frames
        # a wrong marker count is the model's to name ("model expects 150 markers, got 149")
        if self.reference is not None and frames.shape[1:] == self.reference.rest.shape:
            self.reference.check(frames)
        return self.model.synthesize(markers, outputs, clamp, **options)

    def __getattr__(self, name: str) -> Any:
        return getattr(self.model, name)


@dataclass
class Preload:
    """A background preload (:meth:`Services.start_preload`) and how far it got.

    Attributes
    ----------
    models : list[str]       the model ids to load, in order
    loaded : list[str]       those loaded so far
    error : str | None       why a load failed (the thread stops there)
    done : threading.Event   set when every model is loaded or one failed
    """

    models: list[str]
    loaded: list[str] = field(default_factory=list)
    error: str | None = None
    done: threading.Event = field(default_factory=threading.Event, repr=False)

    def status(self) -> str:
        """``"ok"`` once every model is loaded, else what /readyz says instead."""
        if self.error is not None:
            return f"preload failed: {self.error}"
        if self.done.is_set():
            return "ok"
        return f"loading: {len(self.loaded)} of {len(self.models)} preloaded"


@dataclass
class Services:
    """The store and model cache of one process.

    Build it with :meth:`open`; :meth:`close` disposes of the engine's connections.

    Attributes
    ----------
    settings : Settings
    store : Store               the process's database + blob container (shared with jobs)
    models : ByteLRUCache      loaded models by id, within ``settings.model_cache_bytes``
    registrations : ByteLRUCache   loaded input-rig registrations by (rig id, sha256)
    synthesis : SynthesisPool  the process's synthesis slots, shared by the HTTP routes
                               (:class:`~service.app.synthesis.Synthesizer`) and the gRPC
                               streams (None when built: ``max_concurrent_syntheses`` of them)
    """

    settings: Settings
    store: Store
    models: ByteLRUCache[LoadedModel] = field(repr=False)
    registrations: ByteLRUCache[Any] = field(
        default_factory=lambda: ByteLRUCache(REGISTRATION_CACHE_BYTES), repr=False)
    #: write-once blobs (keys, or files of model directories) this process has verified
    verified_blobs: set[str] = field(default_factory=set, repr=False)
    #: marker layouts on their neutrals by (actor id, neutral sha256, layout sha256), for the
    #: unit check of marker requests (at most 64, newest first)
    marker_references: dict[tuple, Any] = field(default_factory=dict, repr=False)
    #: the background preload of ``facesynth serve`` (None: none was asked for)
    preloading: Preload | None = field(default=None, repr=False)
    #: the job threads ``facesynth serve`` runs beside the API (None: another process's)
    job_threads: JobThreads | None = field(default=None, repr=False)
    #: ready models' rows by id, as last read (:data:`READY_RECHECK_SECONDS`)
    ready_rows: dict[str, ReadyRow] = field(default_factory=dict, repr=False)
    #: models forgotten so far: a row read before a deletion is not remembered after it
    forgotten: int = field(default=0, repr=False)
    synthesis: SynthesisPool = field(default=None, repr=False)  # type: ignore[assignment]

    def __post_init__(self) -> None:
        if self.synthesis is None:
            self.synthesis = SynthesisPool(
                self.settings.max_concurrent_syntheses,
                share_cores=cores() if self.settings.synthesis_kernel_threads == "share" else None)

    @classmethod
    def open(cls, settings: Settings, synthesis: SynthesisPool | None = None) -> "Services":
        """Connect to the database of ``settings`` (running the migrations), open the blob
        store and make an empty model cache; ``synthesis``: the synthesis slots to share
        (None: a pool of ``max_concurrent_syntheses``)."""
        settings.data_dir.mkdir(parents=True, exist_ok=True)
        return cls(settings=settings, store=get_store(settings, migrate=True),
                   models=ByteLRUCache(settings.model_cache_bytes), synthesis=synthesis)

    @property
    def engine(self) -> Engine:
        return self.store.engine

    @property
    def blobs(self) -> BlobStore:
        return self.store.blobs

    def close(self) -> None:
        """Drop the cached models and the database connections, and stop the synthesis
        pool's threads (calls not started are cancelled)."""
        self.synthesis.shutdown(wait=False, cancel_futures=True)
        self.models.clear()
        self.registrations.clear()
        self.ready_rows.clear()
        self.store.dispose()

    def session(self) -> contextlib.AbstractContextManager[Session]:
        """A database session, closed (and any open transaction rolled back) on exit."""
        return self.store.session()

    def load_model(self, model_id: str) -> Any:
        """The loaded model ``model_id`` for the gRPC server: the model object, its marker
        frames checked for the actor's unit first when it takes markers
        (:class:`UnitCheckedModel`, as ``/synthesize`` checks them)."""
        return self.loaded_model(model_id).stream

    def loaded_model(self, model_id: str) -> LoadedModel:
        """A ready model from the cache, loading it (checksums verified) on a miss.

        Its row is read at most every :data:`READY_RECHECK_SECONDS` while the model stays
        cached (a deletion in this process is seen at once, one by another process within
        that time); the tenant of the request is checked on every call.

        Raises
        ------
        NotFound   unknown (or malformed) model id, or one of another tenant
        Conflict   the model is training or failed, so it cannot synthesize
        """
        row = self.ready_rows.get(model_id)
        if (row is not None and time.monotonic() - row.checked < READY_RECHECK_SECONDS
                and model_id in self.models):
            in_tenant(row, "model", None)   # another tenant's: the NotFound of an unknown id
            # (evicted since the check above: the loader reads the row again, as a miss does)
            return self.models.get_or_load(model_id, lambda: self._load(model_id, row),
                                           size_of=self._size_of(row))
        forgotten = self.forgotten
        with self.session() as session:
            model = registry.get_model(session, model_id)
            if model.status != "ready":
                what = ("still training; it can synthesize once its training job succeeds"
                        if model.status == "training" else
                        f"{model.status}{': ' + model.error['message'] if model.error else ''}")
                raise Conflict(f"model {model_id!r} is not ready: it is {what}")
            row = ReadyRow(model_id, model.tenant, model.kind, model.actor_id,
                           int(model.size_bytes or 0), time.monotonic())
        loaded = self.models.get_or_load(model_id, lambda: self._load(model_id, row),
                                         size_of=self._size_of(row))
        if forgotten == self.forgotten:     # no deletion since the read: remember it
            self.ready_rows.pop(model_id, None)
            while len(self.ready_rows) >= READY_ROWS:
                self.ready_rows.pop(next(iter(self.ready_rows)), None)
            self.ready_rows[model_id] = row
        return loaded

    def _size_of(self, row: ReadyRow) -> Callable[[LoadedModel], int]:
        """What the cache weighs a loaded model of ``row`` by: what it holds in memory
        (arrays, operators, factorizations, :func:`~service.methods.footprint.nbytes`), which
        can be several times its files (a shape-space model's prefactored solves) or less
        (files it maps and reads in part, data it reads once at load).

        Not at least its files any more (issue 23): a level-1 PDM's 414 MB of files (the
        medium map and EXRs it never holds) outweighed its resident cost, 322 MB after a
        mesh + displacement + normal-map frame and 348 MB after one of every output, by
        1.19–1.29×; weighed by what it holds, 350 MB: 1.09× and 1.01×
        (``benchmarks/cold_start.py --footprint``)."""
        kind = get_kind(row.kind)
        return lambda loaded: nbytes(loaded.model, mapped=kind.weighs_mapped)

    def _load(self, model_id: str, row: ReadyRow) -> LoadedModel:
        """Load the ready model of ``row`` from its verified files.

        The integrity rule: the files are hashed in a thread while the kind reads them (the
        cold start overlaps the two), and nothing read from them is synthesized with — no
        warm-up frame, no request, no stream — or cached before :meth:`VerifyingDir.confirm`
        has matched every file to the recorded sha256; a mismatch raises ``BlobCorrupt``
        (500 / DATA_LOSS / a failed preload) and nothing is cached. Not overlapped further on
        purpose: a corrupt index array read by a compiled (unchecked) kernel could write out
        of bounds, so synthesis waits for the check."""
        kind = get_kind(row.kind)
        with self.session() as session:
            # the files are hashed in a thread while the kind reads them (issue 23's cold
            # start); nothing loaded is used before confirm() has checked them. model_dir
            # reads the row again (NotFound, Conflict as loaded_model's)
            path = registry.model_dir(session, self.blobs, model_id, background=True)
        log.info("loading model %s (%s, %d bytes)", model_id, kind.name, row.size_bytes)
        try:
            model = kind.load(path)
        except Exception:
            path.confirm()   # a corrupt file is reported as corrupt, not as what it broke
            raise
        path.confirm()
        # a load's temporaries (file bytes, decoded maps, operator assembly) are about
        # as large as the model: hand the freed heap back so that the resident cost
        # is the model's (what the cache weighs by), not its peak
        release_free_heap()
        reference = self.marker_reference(row.actor_id)
        stream = UnitCheckedModel(model, reference) if kind.input == "markers" else model
        return LoadedModel(model_id, kind, model, row.actor_id, stream, reference=reference)

    def preload(self, models: Sequence[str]) -> list[str]:
        """Load models into the cache before the first request needs them (a stream's first
        frame otherwise waits for the load: 7.7 s for a level-1 PDM).

        Parameters
        ----------
        models : model ids, or ``["all"]`` for every ready model (oldest first; the cache's
                 byte budget still applies, so the last ones loaded are the ones kept)

        Returns
        -------
        list[str]   the ids loaded

        Raises
        ------
        NotFound, Conflict   a named model is unknown or not ready
        """
        loaded = []
        for model_id in self.preload_ids(models):
            self.loaded_model(model_id)
            loaded.append(model_id)
        log.info("preloaded %d model(s): %s", len(loaded), ", ".join(loaded) or "none",
                 extra={"cache_bytes": self.models.total_bytes,
                        "cache_models": len(self.models)})
        return loaded

    def preload_ids(self, models: Sequence[str]) -> list[str]:
        """The model ids a preload of ``models`` loads (``["all"]``: every ready model,
        oldest first), each checked to exist and be ready.

        Raises
        ------
        NotFound, Conflict   a named model is unknown or not ready
        """
        with self.session() as session:
            if list(models) == ["all"]:
                return [m.id for m in registry.list_models(session, status="ready")]
            for model_id in models:
                row = registry.get_model(session, model_id)
                if row.status != "ready":
                    raise Conflict(f"model {model_id!r} is {row.status}, not ready")
        return list(models)

    def start_preload(self, models: Sequence[str]) -> Preload:
        """Check ``models`` now (as :meth:`preload_ids`), then load them in a background
        thread while the process serves; ``check()`` reports ``models`` not ready until they
        are loaded (or names the load that failed). The first request of a preloaded model
        then waits for no load (issue 23: 7.7 s for a level-1 PDM otherwise).

        Raises
        ------
        NotFound, Conflict   a named model is unknown or not ready (before anything loads)
        """
        state = Preload(self.preload_ids(models))
        self.preloading = state

        def run() -> None:
            warmed = []
            try:
                for model_id in state.models:
                    warmed.append(self.loaded_model(model_id))
                    self.warm_up(warmed[-1])
                    state.loaded.append(model_id)
                log.info("preloaded %d model(s): %s", len(state.loaded),
                         ", ".join(state.loaded) or "none",
                         extra={"cache_bytes": self.models.total_bytes,
                                "cache_models": len(self.models)})
            except Exception as error:  # noqa: BLE001 - reported by /readyz and the log
                state.error = f"{model_id}: {type(error).__name__}: {error}"
                log.error("preload of %s failed: %s", model_id, error)
            finally:
                state.done.set()
            for loaded in warmed[:len(state.loaded)]:   # once ready: the first frame does not wait
                self.warm_up(loaded, half=True)

        threading.Thread(target=run, name="facesynth-preload", daemon=True).start()
        return state

    def warm_up(self, loaded: LoadedModel, half: bool = False) -> bool:
        """Synthesize one neutral frame (the actor's marker layout on its neutral, or the
        neutral itself for mesh-driven kinds) with the mesh and the maps, and drop it: the
        first request after a preload then finds the model's memory-mapped arrays paged in
        and every code path imported, the float16 conversion of ``half=true`` too (measured on the level-1 PDM under load: the first
        frame took 1.9 s after a preload without it, 8× the next ones). With ``half``, the
        same frame with the maps written as float16 by the model where it takes ``half``
        (the kernels of a half-precision stream or answer: ~3.4 s to compile without Numba's
        disk cache); :meth:`start_preload` runs it once the model is ready. Returns whether a
        frame was synthesized; a failure is logged, never raised (the model is loaded)."""
        try:
            if loaded.kind.input == "markers":
                reference = self.marker_reference(loaded.actor_id)
                if reference is None:
                    return False
                frame = reference.rest[None]
            else:
                with self.session() as session:
                    frame = neutral_arrays(registry.read_neutral(session, self.blobs, loaded.actor_id))[0][None]
            outputs = [o for o in ("mesh", "displacement", "normal_map") if o in loaded.kind.outputs]
            maps = bool({"displacement", "normal_map"} & set(outputs))
            if half and not (maps and takes(loaded.model, "half")):
                return False
            loaded.model.synthesize(np.asarray(frame, np.float64), outputs, **({"half": True} if half else {}))
            if maps and not half:
                # the compiled float16 conversion of half=true responses, loaded from its
                # on-disk cache now rather than by the first such request
                from service.io.half import to_float16

                to_float16(np.zeros(1, np.float32))
        except Exception as error:  # noqa: BLE001 - a warm-up is an optimization
            log.warning("warm-up of model %s failed: %s: %s", loaded.id, type(error).__name__, error)
            return False
        release_free_heap()
        return True

    def marker_reference(self, actor_id: str | None) -> MarkerReference | None:
        """The actor's marker layout on its neutral (cached by the two blobs' digests), or
        None without an actor, a neutral or a layout."""
        if actor_id is None:
            return None
        with self.session() as session:
            actor = registry.get_actor(session, actor_id)
            if actor.neutral_blob is None or actor.markers_blob is None:
                return None
            key = (actor_id, actor.neutral_sha256, actor.markers_sha256)
            cached = self.marker_references.get(key)
            if cached is None:
                V, F = neutral_arrays(registry.read_neutral(session, self.blobs, actor_id))
                layout = json.loads(registry.read_markers(session, self.blobs, actor_id))
                rest = layout_positions(V, F, np.asarray(layout["triangle"]),
                                        np.asarray(layout["barycentric"]))
                cached = MarkerReference(rest, face_unit(rest, (actor.meta or {}).get("units")))
                self.marker_references = {key: cached, **dict(list(self.marker_references.items())[:63])}
            return cached

    def forget_model(self, model_id: str) -> None:
        """Drop a (deleted) model from the cache, and its row: the next request reads it
        (and answers 404) at once."""
        self.forgotten += 1
        self.ready_rows.pop(model_id, None)
        self.models.invalidate(model_id)

    def check(self) -> dict[str, str]:
        """Readiness of the database, the blob store, the job queue (its storage probed
        without Huey: :func:`service.jobs.queue_storage.probe`), (while a background preload
        runs, :meth:`start_preload`) the preloaded models, and (``workers``, only when it
        happened) the failed start of this process's job threads (:attr:`job_threads`).

        Returns
        -------
        dict   component → ``"ok"`` or the reason it is not
        """
        status: dict[str, str] = {}
        try:
            with self.session() as session:
                session.execute(text("SELECT 1"))
            status["database"] = "ok"
        except Exception as error:  # noqa: BLE001 - any failure means "not ready"
            status["database"] = f"unreachable: {type(error).__name__}: {error}"
        if not self.blobs.root.is_dir():
            status["blobs"] = "the blob store's directory is missing"
        else:      # writable, with min_free_bytes free (no server paths in the answer)
            health = self.blobs.health(self.settings.min_free_bytes)
            status["blobs"] = "ok" if health.ready else health.reason
        status["queue"] = _queue_status(self.settings)
        if self.preloading is not None:
            status["models"] = self.preloading.status()
        if self.job_threads is not None and self.job_threads.error is not None:
            status["workers"] = self.job_threads.status()
        return status


def _queue_status(settings: Settings) -> str:
    """``"ok"`` if the job queue's storage answers, else why not (no Huey imported: issue
    23's cold start, :mod:`service.jobs.queue_storage`)."""
    try:
        probe_queue(settings)
    except Exception as error:  # noqa: BLE001 - any failure means "not ready"
        return f"unreachable: {type(error).__name__}: {error}"
    return "ok"
