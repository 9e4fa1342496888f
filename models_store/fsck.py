"""Consistency check of the blob store against the database: orphans and missing blobs.

The registry writes a blob before the row that references it and deletes a replaced blob
only after the commit that stops referencing it (:mod:`models_store.registry`), so a crash
can leave an unreferenced blob (an *orphan*), never a row pointing at nothing. :func:`fsck`
finds both kinds of inconsistency:

- orphans: stored blobs (files, or whole directories such as a model attempt's) that no
  row and no job payload references;
- missing: rows whose blob is not in the store (a fault outside the registry: a lost disk,
  a hand-deleted file).

With ``remove=True`` it deletes the orphans older than ``min_age`` seconds (newest
modification time in the blob); younger ones are reported but kept, because a blob is
written shortly *before* the row that will reference it is committed. Hidden names are
temporaries, the business of :meth:`~models_store.blobs.BlobStore.sweep_temporaries`.
``facesynth store fsck [--remove]`` runs it.
"""

from __future__ import annotations

import os
import time
from dataclasses import dataclass, field
from pathlib import Path

from sqlalchemy import select
from sqlalchemy.orm import Session

from models_store.blobs import _SEGMENT, BlobStore, _newest_mtime
from models_store.schema import Actor, Artifact, Clip, InputRig, Job, Model

#: orphans younger than this (seconds) are kept: their row may be about to be committed
DEFAULT_MIN_AGE = 3600.0


@dataclass
class FsckReport:
    """What :func:`fsck` found (keys are blob keys, ``/``-separated).

    Attributes
    ----------
    orphans : list of str       unreferenced blobs (files or directories)
    removed : list of str       the orphans deleted (``remove=True``, old enough)
    kept_young : list of str    orphans kept because younger than ``min_age``
    missing : list of (str, str, str)   (table, row id, key) of referenced blobs not stored
    referenced : int            how many blob keys the database references
    """

    orphans: list[str] = field(default_factory=list)
    removed: list[str] = field(default_factory=list)
    kept_young: list[str] = field(default_factory=list)
    missing: list[tuple[str, str, str]] = field(default_factory=list)
    referenced: int = 0

    @property
    def clean(self) -> bool:
        return not self.orphans and not self.missing


def referenced_keys(session: Session) -> dict[str, tuple[str, str]]:
    """Every blob key the database references → (table, row id)."""
    keys: dict[str, tuple[str, str]] = {}
    columns = [(Actor, Actor.neutral_blob), (Actor, Actor.markers_blob), (Clip, Clip.blob),
               (InputRig, InputRig.mesh_blob), (InputRig, InputRig.registration_blob),
               (Model, Model.blob), (Artifact, Artifact.blob)]
    for table, column in columns:
        for row_id, key in session.execute(select(table.id, column).where(column.isnot(None))):
            keys[key] = (table.__tablename__, row_id)
    # synthesis inputs and input-rig registrations named by job payloads ("*_blob")
    for job_id, payload in session.execute(select(Job.id, Job.payload)):
        for name, value in (payload or {}).items():
            if name.endswith("_blob") and isinstance(value, str) and value:
                keys.setdefault(value, ("jobs", job_id))
    return keys


def fsck(session: Session, blobs: BlobStore, *, remove: bool = False,
         min_age: float = DEFAULT_MIN_AGE, now: float | None = None) -> FsckReport:
    """Compare the blob store with the database (see the module docstring).

    Parameters
    ----------
    remove : bool     delete the orphans older than ``min_age``
    min_age : float   seconds; younger orphans are never deleted
    now : float       the current time (``time.time()``; for tests)
    """
    now = time.time() if now is None else now
    keys = referenced_keys(session)
    report = FsckReport(referenced=len(keys))
    # every prefix of a referenced key is a directory to look into, not an orphan
    prefixes = {"/".join(key.split("/")[:i]) for key in keys for i in range(1, key.count("/") + 1)}
    for dirpath, dirnames, filenames in os.walk(blobs.root):
        rel_dir = Path(dirpath).relative_to(blobs.root).as_posix()
        rel = (lambda name: name) if rel_dir == "." else (lambda name: f"{rel_dir}/{name}")
        keep = []
        for name in sorted(dirnames):
            key = rel(name)
            if not _SEGMENT.fullmatch(name) or key in keys:
                continue              # a temporary (or lost+found), or a directory blob
            if key in prefixes:
                keep.append(name)                          # holds referenced blobs: look in
            elif any(p.is_file() for p in Path(dirpath, name).rglob("*")):
                report.orphans.append(key)                 # (an empty directory is no blob)
        dirnames[:] = keep
        report.orphans.extend(rel(name) for name in sorted(filenames)
                              if _SEGMENT.fullmatch(name) and rel(name) not in keys)
    report.orphans.sort()
    for table_key, (table, row_id) in sorted(keys.items()):
        if not blobs.path(table_key).exists():
            report.missing.append((table, row_id, table_key))
    if remove:
        for key in report.orphans:
            path = blobs.root / key
            try:
                young = now - _newest_mtime(path) < min_age
            except FileNotFoundError:
                continue
            if young:
                report.kept_young.append(key)
            elif blobs.delete(key):
                report.removed.append(key)
    return report
