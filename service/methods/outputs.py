"""The synthesis output vocabulary (API.md "Synthesis"), declared once.

Every model kind synthesizes a subset of :data:`OUTPUTS` (its ``Kind.outputs``); the HTTP
schemas, the gRPC codec, the synthesis jobs and the methods all take the names from here.
"""

from __future__ import annotations

from typing import Literal, Sequence

from service.errors import InvalidInput

#: one output name (API.md: ``outputs`` ⊆ these)
Output = Literal["mesh", "mesh_detailed", "displacement", "albedo", "normal_map"]
#: every output the service knows, in the order responses list them
OUTPUTS: tuple[str, ...] = ("mesh", "mesh_detailed", "displacement", "albedo", "normal_map")
#: the outputs that are UV-space maps (F,H,W[,3])
MAP_OUTPUTS: tuple[str, ...] = ("displacement", "albedo", "normal_map")
#: outputs of a request or job that names none (API.md)
DEFAULT_OUTPUTS: tuple[str, ...] = ("mesh", "displacement")
#: outputs of a gRPC stream whose first message names none: a live preview's cheapest frame
STREAM_DEFAULT_OUTPUTS: tuple[str, ...] = ("mesh",)


def check_outputs(names: Sequence[str], known: Sequence[str] = OUTPUTS) -> tuple[str, ...]:
    """``names`` without repeats, in the given order; :class:`InvalidInput` naming those
    not in ``known`` (a kind's own subset, or every output)."""
    unknown = sorted(set(names) - set(known))
    if unknown:
        raise InvalidInput(f"unknown outputs {unknown}; choose from {list(known)}")
    return tuple(dict.fromkeys(names))
