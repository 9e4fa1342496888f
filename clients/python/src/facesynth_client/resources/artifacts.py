"""``client.artifacts``: job results, downloaded or read (``/v1/artifacts/{artifact_id}``)."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from .. import arrays as A
from .._core import Call, Op
from ._base import Resource

__all__ = ["Artifacts"]


class Artifacts(Resource):
    """``/v1/artifacts/{artifact_id}``: job results."""

    def download(self, artifact_id: str, path: str | os.PathLike, *, resume: bool = True,
                 sha256: str | None = None) -> Path:
        """Stream an artifact to ``path``.

        Written to ``<path>.part`` and renamed once complete, so ``path`` never holds a
        partial file; checked against ``Content-Length`` and its sha256 (the server's ETag,
        or ``sha256``). An interrupted download is resumed with a range request (also on
        the next call, from the ``.part`` file, while the ETag is unchanged).

        Returns
        -------
        pathlib.Path

        Raises
        ------
        IntegrityError   the content does not match its sha256

        Examples
        --------
        >>> client.artifacts.download(job.artifact_ids[0], "out/take7.npz")   # doctest: +SKIP
        """
        return self._run(self._core.download(f"/v1/artifacts/{artifact_id}", path,
                                              expected_sha256=sha256, resume=resume))

    def read(self, artifact_id: str) -> bytes:
        """An artifact's bytes, in memory."""
        return self._run(self._core.call_bytes(Call("GET", f"/v1/artifacts/{artifact_id}",
                                                    headers={"Accept": "*/*"})))

    def arrays(self, artifact_id: str) -> dict[str, np.ndarray]:
        """An ``.npz`` artifact's arrays (read with ``allow_pickle=False``)."""
        return self._run(self._load(artifact_id))

    def _load(self, artifact_id: str) -> Op:
        content = yield from self._core.call_bytes(
            Call("GET", f"/v1/artifacts/{artifact_id}", headers={"Accept": "*/*"}))
        return A.load_npz(content)
