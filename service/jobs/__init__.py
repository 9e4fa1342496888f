"""Jobs: long work (training, synthesis of whole performances, ...) run by workers.

The job rows in the database (:mod:`models_store.registry`) are the truth about every job:
``queued → running`` (with progress and stage) ``→ succeeded | failed | cancelled``. Huey is
only the transport that tells a worker "job <id> is waiting"; a lost or duplicated message
is harmless, because a worker runs a job only after claiming its row.

- :mod:`.context`     the database sessions and blob store of a :class:`~service.config.Settings`
- :mod:`.queue`       the Huey instance (SQLite file by default, Redis by URL), its JSON
  serializer, the one task ``run_job(job_id)`` and :func:`~.queue.submit`
- :mod:`.runner`      :func:`~.runner.execute`: claim, heartbeat, progress and cancellation,
  finish — the lifecycle around one task function
- :mod:`.tasks`       one function per job kind (``train``, ``synthesize``)
- :mod:`.frame_npz`   NPZ results written frame chunk by frame chunk (bounded memory)
- :mod:`.worker`      :func:`~.worker.run_worker` (``facesynth worker``) and
  :func:`~.worker.start_embedded` (``facesynth serve``): the consumer plus the reaper that
  requeues jobs whose worker died
- :mod:`.queue_storage`  the queue URL's form and a probe of its storage, without Huey
  (``/readyz``, ``facesynth check``, serve's start)
- :mod:`.job_threads`  serve's embedded workers or maintenance thread, started at once or
  after a preload (Huey imported only then)
"""
