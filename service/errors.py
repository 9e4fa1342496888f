"""Every error the server raises on purpose, by meaning (one root: :class:`FacesynthError`).

The meanings are declared once in :mod:`models_store.errors` (the lowest package, so the
store raises them too); the file-format errors of :mod:`service.io.errors` are
:class:`InvalidInput` (and :class:`PayloadTooLarge` for declared sizes over a limit).
Import errors from here.
"""

from __future__ import annotations

from typing import Any, Iterable, Mapping, Sequence

from pydantic import ValidationError

from models_store.errors import (
    BlobCorrupt, Conflict, Corrupt, FacesynthError, InsufficientStorage, InvalidId, InvalidInput,
    MalformedInput, NotAcceptable, NotFound, PayloadTooLarge, Unavailable, UnsupportedFormat,
)

__all__ = ["BlobCorrupt", "Conflict", "Corrupt", "FacesynthError", "InsufficientStorage",
           "InvalidId", "InvalidInput", "MalformedInput", "NotAcceptable", "NotFound",
           "PayloadTooLarge", "Unavailable", "UnsupportedFormat", "field_errors", "invalid_fields",
           "summary"]


def field_errors(errors: Iterable[Mapping[str, Any]], prefix: tuple = ()) -> list[dict[str, Any]]:
    """Pydantic errors as JSON-safe ``{loc, msg, type}`` (no inputs, no exception objects)."""
    return [{"loc": [*prefix, *(e.get("loc") or ())], "msg": str(e.get("msg", "")),
             "type": str(e.get("type", ""))} for e in errors]


def summary(errors: Sequence[Mapping[str, Any]]) -> str:
    """One line naming the first of ``errors`` (``{loc, msg}``) and how many there are."""
    first = errors[0]
    where = ".".join(str(part) for part in first["loc"])
    more = f" (and {len(errors) - 1} more)" if len(errors) > 1 else ""
    return f"{where}: {first['msg']}{more}" if where else first["msg"] + more


def invalid_fields(error: ValidationError, prefix: tuple = ("body",)) -> InvalidInput:
    """The :class:`InvalidInput` (with per-field ``errors``) for a body that fails its schema."""
    errors = field_errors(error.errors(include_url=False, include_input=False), prefix)
    return InvalidInput(summary(errors), errors)
