"""A check every kind's store test shares: a directory the blob store verified is read
without hashing its files a second time."""

from __future__ import annotations

from pathlib import Path
from types import SimpleNamespace
from typing import Any, Callable

from models_store.atomic import sha256_file
from models_store.blobs import VerifiedDir
from service.methods import model_dir


def load_verified_without_hashing(load: Callable[[Any], Any], path: Path, monkeypatch) -> Any:
    """``load(dir)`` of the model directory ``path`` handed over as the blob store hands it
    (:class:`~models_store.blobs.VerifiedDir`, with the digests it verified), with every
    hashing in :mod:`service.methods.model_dir` failing: the kind's reader must pass the
    directory on as given, so that its manifest is compared with those digests (issue 23:
    the readers' ``Path(path)`` dropped them and every load hashed the whole model a second
    time, 0.3 s of a level-1 PDM's)."""
    verified = VerifiedDir.of(path, {p.name: sha256_file(p) for p in Path(path).iterdir()})

    def no_hashing(*args):
        raise AssertionError("the verified directory was hashed a second time")

    with monkeypatch.context() as patch:
        patch.setattr(model_dir, "sha256_file", no_hashing)
        patch.setattr(model_dir, "hashlib", SimpleNamespace(sha256=no_hashing))
        return load(verified)
