"""Query strings, checked once for every route: unknown parameters are refused, and every
list route pages its items with ``limit`` and ``cursor``.

Unknown parameters. :func:`reject_unknown_query` is an app-wide dependency. It reads the
query parameters the matched route declares (its own and its dependencies', by alias) and
answers a 422 problem naming each parameter it does not know, with the ``errors`` entry
``{"loc": ["query", name], "type": "extra_forbidden"}`` that a JSON body with an unknown field
gets; a misspelt ``?outptus=mesh`` is refused instead of being silently ignored.

Pagination. :data:`PageDep` declares ``limit`` (1..:data:`MAX_LIMIT`, default
:data:`DEFAULT_LIMIT`) and ``cursor``. A list answers at most ``limit`` items and, when more
follow, ``next_cursor``: send it back as ``cursor`` for the next page. Cursors are opaque
(the base64url JSON of the last item's sort key, see :mod:`models_store.registry.paging`),
keyset-based, so pages neither skip nor repeat items while items are added or deleted.
"""

from __future__ import annotations

import base64
import binascii
import json
from dataclasses import dataclass
from typing import Annotated, Any, Callable, Sequence, TypeVar

from fastapi import Depends, Query, Request
from fastapi.dependencies.models import Dependant
from fastapi.exceptions import RequestValidationError
from fastapi.routing import APIRoute

from models_store.registry.paging import check_key, sort_key
from models_store.schema import Base

T = TypeVar("T")

DEFAULT_LIMIT = 100
MAX_LIMIT = 1000

_KNOWN: dict[int, frozenset[str]] = {}


def declared_query(route: APIRoute) -> frozenset[str]:
    """The query parameter names (aliases) that ``route`` and its dependencies declare."""
    known = _KNOWN.get(id(route))
    if known is None:
        known = _KNOWN[id(route)] = frozenset(_query_aliases(route.dependant))
    return known


def _query_aliases(dependant: Dependant) -> set[str]:
    """The query aliases of ``dependant`` and of its sub-dependencies, recursively."""
    names = {field.alias for field in dependant.query_params}
    for sub in dependant.dependencies:
        names |= _query_aliases(sub)
    return names


async def reject_unknown_query(request: Request) -> None:
    """Refuse (422, ``extra_forbidden``) each query parameter the route does not declare
    (``async``: it runs on the event loop, without a thread-pool hand-off, as
    :mod:`service.api.deps` explains)."""
    route = request.scope.get("route")
    if not isinstance(route, APIRoute):
        return
    known = declared_query(route)
    unknown = [name for name in dict.fromkeys(request.query_params.keys()) if name not in known]
    if unknown:
        expected = ", ".join(sorted(known)) or "none"
        raise RequestValidationError([
            {"loc": ("query", name), "type": "extra_forbidden",
             "msg": f"unknown query parameter {name!r} (this route takes: {expected})"}
            for name in unknown])


@dataclass(frozen=True)
class Page:
    """One page request: at most ``limit`` items after the sort key ``after``."""

    limit: int
    after: list[str] | None

    def fetch(self, row_type: type[Base]) -> dict[str, Any]:
        """Keyword arguments for a registry ``list_*`` call of ``row_type`` rows: one row
        more than the page, which tells whether another page follows (a 422 naming
        ``cursor`` if it is not a key of ``row_type``)."""
        if self.after is not None:
            try:
                check_key(row_type, self.after)
            except ValueError:
                raise _bad_cursor() from None
        return {"after": self.after, "limit": self.limit + 1}

    def rows(self, rows: Sequence[T]) -> tuple[list[T], str | None]:
        """The page of registry ``rows`` (fetched with :meth:`fetch`) and its ``next_cursor``."""
        return self._cut(list(rows), sort_key)

    def items(self, items: Sequence[T], key: Callable[[T], str]) -> tuple[list[T], str | None]:
        """A page of an in-memory listing (in its own order) whose items have the unique
        string ``key``: the items after the one the cursor names (a 422 if none has it)."""
        start = 0
        if self.after is not None:
            keys = [key(item) for item in items]
            if len(self.after) != 1 or self.after[0] not in keys:
                raise _bad_cursor()
            start = keys.index(self.after[0]) + 1
        return self._cut(list(items[start:start + self.limit + 1]), lambda item: [key(item)])

    def _cut(self, rows: list[T], key: Callable[[T], list[str]]) -> tuple[list[T], str | None]:
        if len(rows) <= self.limit:
            return rows, None
        page = rows[:self.limit]
        return page, encode_cursor(key(page[-1]))


def encode_cursor(key: Sequence[str]) -> str:
    """The opaque cursor of a sort key."""
    return base64.urlsafe_b64encode(json.dumps(list(key)).encode()).decode().rstrip("=")


def decode_cursor(cursor: str) -> list[str]:
    """The sort key of a cursor; a 422 naming ``cursor`` when it is not one of ours."""
    try:
        key = json.loads(base64.urlsafe_b64decode(cursor + "=" * (-len(cursor) % 4)))
        if not (isinstance(key, list) and key and all(isinstance(k, str) for k in key)):
            raise ValueError("not a key")
        return key
    except (ValueError, binascii.Error, UnicodeDecodeError):
        raise _bad_cursor() from None


def _bad_cursor() -> RequestValidationError:
    return RequestValidationError([{
        "loc": ("query", "cursor"), "type": "value_error",
        "msg": "not a cursor of this listing (send back a response's next_cursor as it is)"}])


async def get_page(
    limit: Annotated[int, Query(ge=1, le=MAX_LIMIT, description=(
        f"At most this many items (default {DEFAULT_LIMIT}); when more follow, the answer "
        "has `next_cursor`."))] = DEFAULT_LIMIT,
    cursor: Annotated[str | None, Query(max_length=2048, description=(
        "The `next_cursor` of the previous page, sent back unchanged; omit it for the first "
        "page."))] = None,
) -> Page:
    """The page a list request asks for (FastAPI dependency)."""
    return Page(limit=limit, after=decode_cursor(cursor) if cursor is not None else None)


PageDep = Annotated[Page, Depends(get_page)]
