"""Reading a stored model directory of any kind: manifest first, every file checksummed.

A model directory (DESIGN.md "Data and storage") holds ``manifest.json`` with ``kind``,
``format_version``, and the sha256 of every file under ``files`` (and, for optional derived
data, ``derived``). Each kind's ``store`` module writes its own files; this module reads any
of them back once, verifying each checksum before a byte is parsed (or, in a directory the
blob store verifies while it is read, before the model is used).
"""

from __future__ import annotations

import hashlib
import json
from pathlib import Path
from typing import Callable

from service.io.atomic import sha256_file
from service.errors import Corrupt


class ModelCorrupt(Corrupt, ValueError):
    """A stored model is incomplete, altered, or of an unknown format."""


def read_model_files(path, kind: str, format_version: int,
                     required: tuple[str, ...] = (), mapped: Callable[[str], bool] | None = None
                     ) -> tuple[dict, dict[str, bytes | Path]]:
    """The manifest of the model directory ``path`` and the bytes of every file it lists.

    ``mapped(name)`` true: that file is checksummed as it streams past (a MiB at a time) and
    its :class:`~pathlib.Path` is returned instead of its bytes, for the caller to map
    (:func:`service.io.npz.npz_mapped`) or read only if it needs it: a load then never
    holds a file's bytes and its decoded arrays at once.

    When ``path`` carries the digests of its files as just verified (``path.digests``, a
    :class:`models_store.blobs.VerifiedDir` from the blob store, which checked them against
    the database's tree digest), each listed file is compared with its digest there instead
    of being hashed again: the directory is hashed once per load either way. When they are
    still being verified (a :class:`models_store.blobs.VerifyingDir`), the comparison runs
    in its ``confirm()``, which the caller calls before it uses the model.

    Raises :class:`ModelCorrupt` for a missing or unreadable manifest, another kind or
    format, a listed file that is missing or does not match its checksum, or a ``required``
    file the manifest does not list.
    """
    later = getattr(path, "after_verify", None)
    verified: dict[str, str] | None = None if later else getattr(path, "digests", None)
    path = Path(path)
    try:
        manifest = json.loads((path / "manifest.json").read_bytes())
    except (OSError, ValueError) as e:
        raise ModelCorrupt(f"{path}: no readable manifest.json ({e})") from None
    if manifest.get("kind") != kind or manifest.get("format_version") != format_version:
        raise ModelCorrupt(f"{path}: not a {kind} model of format {format_version} "
                           f"(kind {manifest.get('kind')!r}, format {manifest.get('format_version')!r})")
    listed: dict[str, str] = {**manifest.get("files", {}), **manifest.get("derived", {})}
    data: dict[str, bytes | Path] = {}
    actual: dict[str, str] = {}
    for name in listed:
        try:
            if mapped is not None and mapped(name):
                data[name] = path / name
                if verified is None and later is None:
                    actual[name] = sha256_file(data[name])
            else:
                data[name] = (path / name).read_bytes()
                if verified is None and later is None:
                    actual[name] = hashlib.sha256(data[name]).hexdigest()
        except OSError:
            raise ModelCorrupt(f"{path}: {name} is missing") from None

    def compare(digests: dict[str, str]) -> None:
        for name, digest in listed.items():
            if name not in digests:
                raise ModelCorrupt(f"{path}: {name} is missing")
            if digests[name] != digest:
                raise ModelCorrupt(f"{path}: {name} does not match its checksum")

    if later is not None:
        later(compare)
    else:
        compare(verified if verified is not None else actual)
    for name in required:
        if name not in data:
            raise ModelCorrupt(f"{path}: the manifest lists no {name}")
    return manifest, data


def read_regression(arrays, prefix: str):
    """The marker regression (:class:`service.geometry.marker_regression.MarkerRegression`)
    a model file stored as ``prefix`` (its :meth:`~.MarkerRegression.arrays`), None if it has
    none. A model written before the low-rank form stored the full CSR
    (:func:`service.io.npz.sparse_members`): truncated on reading as training truncates."""
    from service.geometry.marker_regression import MEMBERS, MarkerRegression
    from service.io.npz import sparse_matrix

    if f"{prefix}_Pq" in arrays:
        return MarkerRegression(*(arrays[f"{prefix}_{k}"] for k in MEMBERS))
    L = sparse_matrix(arrays, prefix)
    return None if L is None else MarkerRegression.from_matrix(L, arrays[f"{prefix}_mean_u"],
                                                                arrays[f"{prefix}_mean_y"])
