"""Keyset pagination of the registry's listings.

A listing is ordered by a sort key (``(created_at, id)`` for actors, clips, models, jobs and
artifacts; ``(name,)`` for an actor's input rigs). A page is the first ``limit`` rows whose key
is strictly greater than ``after``, the key of the last row of the previous page. Unlike an
offset, a key stays valid while rows are added or deleted: no row is skipped or repeated, and
a deleted last row still marks its place.
"""

from __future__ import annotations

from datetime import datetime
from typing import Any, Sequence

from sqlalchemy import Select, and_, or_
from sqlalchemy.orm import InstrumentedAttribute

from models_store.schema import (Actor, Artifact, Base, Clip, InputRig, Job, Model, Scan,
                                  UTCDateTime)

#: each listed row type → the columns of its sort key, in order
ORDER: dict[type[Base], tuple[InstrumentedAttribute, ...]] = {
    Actor: (Actor.created_at, Actor.id), Clip: (Clip.created_at, Clip.id),
    Model: (Model.created_at, Model.id), Job: (Job.created_at, Job.id),
    Artifact: (Artifact.created_at, Artifact.id), InputRig: (InputRig.name,),
    Scan: (Scan.created_at, Scan.id),
}


def sort_key(row: Base) -> list[str]:
    """The sort key of ``row`` as JSON-safe strings (datetimes in ISO 8601)."""
    values = (getattr(row, column.key) for column in ORDER[type(row)])
    return [v.isoformat() if isinstance(v, datetime) else str(v) for v in values]


def after_key(query: Select, row_type: type[Base], after: Sequence[str] | None,
              limit: int | None) -> Select:
    """``query`` (already ordered by ``ORDER[row_type]``) restricted to rows after the key
    ``after`` and to ``limit`` rows.

    Parameters
    ----------
    after : the :func:`sort_key` of the last row already seen, or None for the first page
    limit : at most this many rows, or None for all

    Raises
    ------
    ValueError   ``after`` does not have the key's length or a datetime part is not ISO 8601
    """
    columns = ORDER[row_type]
    if after is not None:
        values = check_key(row_type, after)
        # (c1, c2, ...) > (v1, v2, ...) lexicographically, spelt out so each comparison
        # binds its value with its column's type (a row-value comparison would not)
        query = query.where(or_(*(and_(*(columns[j] == values[j] for j in range(i)),
                                       columns[i] > values[i]) for i in range(len(columns)))))
    return query.limit(limit) if limit is not None else query


def check_key(row_type: type[Base], key: Sequence[str]) -> list[Any]:
    """The values of a :func:`sort_key` of ``row_type`` (ValueError if it is not one)."""
    columns = ORDER[row_type]
    if len(key) != len(columns):
        raise ValueError(f"a {row_type.__name__} key has {len(columns)} parts, not {len(key)}")
    return [_value(c, v) for c, v in zip(columns, key)]


def _value(column: InstrumentedAttribute, text: str) -> Any:
    """A key part as its column's Python value (an aware datetime for a timestamp)."""
    if not isinstance(column.type, UTCDateTime):
        return str(text)
    value = datetime.fromisoformat(str(text))
    if value.tzinfo is None:
        raise ValueError(f"{text!r} has no time zone")
    return value
