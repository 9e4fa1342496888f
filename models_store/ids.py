"""Record ids: a kind prefix and a 26-character lowercase ULID.

``act_01j9z3k5q8m2v7c4x6b1n0r8te``: the prefix names the kind, the body is a ULID in
lowercase Crockford base32: 48 bits of milliseconds since the epoch (10 characters) then 80
random bits (16 characters). Ids therefore sort by creation time, are unguessable, and use
only ``[0-9a-z]`` without ``i l o u``.

Ids become path components in the blob store, so :func:`validate_id` accepts exactly that
pattern and nothing else (no ``..``, no ``/``, no upper case, no whitespace).
"""

from __future__ import annotations

import re
import secrets
import time

from models_store.errors import InvalidId

#: The Crockford base32 alphabet, lowercase (no i, l, o, u).
ALPHABET = "0123456789abcdefghjkmnpqrstvwxyz"

#: Kind of record → id prefix.
PREFIXES: dict[str, str] = {
    "actor": "act",
    "clip": "clp",
    "model": "mdl",
    "job": "job",
    "artifact": "art",
    "rig": "rig",
    "scan": "scn",
}

_BODY = f"[{ALPHABET}]{{26}}"
_PATTERNS = {kind: re.compile(rf"{prefix}_{_BODY}") for kind, prefix in PREFIXES.items()}


def _encode(value: int, length: int) -> str:
    """``value`` in base32, most significant digit first, zero-padded to ``length``."""
    chars = []
    for _ in range(length):
        value, digit = divmod(value, 32)
        chars.append(ALPHABET[digit])
    return "".join(reversed(chars))


def new_token() -> str:
    """A fresh 26-character ULID (time-ordered, 80 random bits), without a prefix."""
    millis = time.time_ns() // 1_000_000
    return _encode(millis & ((1 << 48) - 1), 10) + _encode(secrets.randbits(80), 16)


def new_id(kind: str) -> str:
    """A fresh id of ``kind`` (one of :data:`PREFIXES`), e.g. ``new_id("actor")``.

    Raises
    ------
    KeyError   for an unknown kind
    """
    return f"{_prefix(kind)}_{new_token()}"


def is_valid_id(kind: str, value: object) -> bool:
    """Whether ``value`` is a well-formed id of ``kind``."""
    return isinstance(value, str) and _PATTERNS[_check_kind(kind)].fullmatch(value) is not None


def validate_id(kind: str, value: object) -> str:
    """Return ``value`` if it is a well-formed id of ``kind``, else raise :class:`InvalidId`.

    Raises
    ------
    InvalidId   naming the kind, the offending value and the expected form
    """
    if not is_valid_id(kind, value):
        raise InvalidId(f"{value!r} is not a valid {kind} id: expected "
                        f"'{_prefix(kind)}_' followed by 26 characters of [{ALPHABET}]")
    return value  # type: ignore[return-value]


def _check_kind(kind: str) -> str:
    if kind not in PREFIXES:
        raise KeyError(f"unknown id kind {kind!r}; known kinds: {', '.join(PREFIXES)}")
    return kind


def _prefix(kind: str) -> str:
    return PREFIXES[_check_kind(kind)]


#: a tenant id: letters, digits, ``._-``, starting with a letter or digit, 1-64 characters
TENANT_PATTERN = re.compile(r"[A-Za-z0-9][A-Za-z0-9._-]{0,63}")


def validate_tenant(value: object) -> str:
    """Return ``value`` if it is a well-formed tenant id, else raise ``ValueError``."""
    if not isinstance(value, str) or not TENANT_PATTERN.fullmatch(value):
        raise ValueError(f"tenant {value!r} must be 1-64 characters [A-Za-z0-9._-] starting "
                         "with a letter or digit")
    return value
