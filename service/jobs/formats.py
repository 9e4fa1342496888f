"""The result formats of a synthesis job (API.md: ``format=``), declared once for the
operation that checks a request and the task that writes the artifact.

``usd`` (:mod:`service.jobs.frame_usd`) is one USD point cache (binary crate ``.usd``) when
the job asks for one mesh output and no maps; with maps (or both ``mesh`` and
``mesh_detailed``) it is a zip of the cache(s) and the per-frame EXR maps they reference.
"""

from __future__ import annotations

from typing import Sequence

from service.errors import InvalidInput
from service.methods.outputs import MAP_OUTPUTS

#: result format → (media type, file suffix) of the artifact
RESULT_FORMATS: dict[str, tuple[str, str]] = {
    "npz": ("application/x-npz", "npz"),
    "obj-exr-zip": ("application/zip", "zip"),
    # a binary USD crate; IANA registers model/vnd.usda (text) and usdz, not the crate
    "usd": ("application/octet-stream", "usd"),
}
#: the artifact of a ``usd`` job whose caches reference maps (or that holds two caches)
USD_ZIP: tuple[str, str] = ("application/zip", "zip")
#: the mesh outputs a USD cache can hold
USD_MESH_OUTPUTS: tuple[str, ...] = ("mesh", "mesh_detailed")


def usd_is_zip(outputs: Sequence[str]) -> bool:
    """Whether a ``usd`` job with ``outputs`` makes a zip (maps asked, or two meshes) rather
    than one ``.usd`` file."""
    return (any(name in MAP_OUTPUTS for name in outputs)
            or sum(name in USD_MESH_OUTPUTS for name in outputs) > 1)


def artifact_type(result_format: str, outputs: Sequence[str]) -> tuple[str, str]:
    """(media type, file suffix) of the artifact of a job in ``result_format``."""
    if result_format == "usd" and usd_is_zip(outputs):
        return USD_ZIP
    return RESULT_FORMATS[result_format]


def check_result_format(result_format: str, outputs: Sequence[str]) -> None:
    """:class:`InvalidInput` for a format this server does not write, or a ``usd`` job
    without a mesh output (a point cache needs points)."""
    if result_format not in RESULT_FORMATS:
        raise InvalidInput(f"result format {result_format!r} is not supported by this server; "
                           f"choose from {list(RESULT_FORMATS)}")
    if result_format == "usd" and not any(name in USD_MESH_OUTPUTS for name in outputs):
        raise InvalidInput(f"format 'usd' is a point cache and needs a mesh output: add 'mesh' "
                           f"or 'mesh_detailed' to the outputs (got {list(outputs)})")
