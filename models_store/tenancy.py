"""Tenants: which tenant a bearer token belongs to, and whether it is an admin token.

Every actor, model and job belongs to a tenant (:mod:`models_store.schema`); a request acts
for the tenant of its token and sees only that tenant's rows — another tenant's ids answer
404, exactly like unknown ones. An *admin* token sees every tenant (operators, the demo).

Tokens are configured in ``FACESYNTH_TOKENS`` (:attr:`service.config.Settings.tokens`), one
entry per token, in one of the forms

==============================  =====================================================
``TOKEN``                       tenant ``default``
``TENANT:TOKEN``                tenant ``TENANT`` (``[A-Za-z0-9._-]``, 1-64 characters)
``TENANT:TOKEN:admin``          an admin token of ``TENANT`` (sees every tenant)
==============================  =====================================================

where ``TOKEN`` is the token itself or, so that configuration files and secret stores need
not hold it, ``sha256:<64 hex digits>``, the SHA-256 of the token (``printf %s "$TOKEN" |
sha256sum``). Tokens cannot contain ``:``. In memory only the digests are kept; a presented
token is hashed and compared with *every* configured digest with
:func:`hmac.compare_digest`, so the time taken does not depend on which token (if any)
matched or how much of it did.
"""

from __future__ import annotations

import hashlib
import hmac
import re
from dataclasses import dataclass
from typing import Iterable, Sequence

from models_store.ids import TENANT_PATTERN
from models_store.schema import DEFAULT_TENANT

_DIGEST = re.compile(r"sha256:([0-9a-fA-F]{64})")


@dataclass(frozen=True)
class Principal:
    """Who a request acts for.

    Attributes
    ----------
    tenant : str   the tenant whose rows it sees and creates
    admin : bool   sees (and may change) every tenant's rows
    """

    tenant: str
    admin: bool = False

    @property
    def scope(self) -> str | None:
        """The ``tenant=`` to pass to :mod:`models_store.registry` (None: every tenant)."""
        return None if self.admin else self.tenant


#: who acts when the server has no tokens (loopback only): the default tenant, as admin
ANONYMOUS = Principal(DEFAULT_TENANT, admin=True)


@dataclass(frozen=True)
class _Entry:
    digest: bytes
    principal: Principal


def digest(token: str) -> bytes:
    """SHA-256 of a token (what is kept and compared)."""
    return hashlib.sha256(token.encode()).digest()


def parse_entry(entry: str) -> tuple[bytes, Principal]:
    """One ``FACESYNTH_TOKENS`` entry → (token digest, principal); ValueError if malformed.

    The error message never contains the token.
    """
    admin = entry.count(":") >= 2 and entry.endswith(":admin")
    rest = entry[:-len(":admin")] if admin else entry
    if _DIGEST.fullmatch(rest):                          # sha256:HEX, tenant default
        tenant, secret = DEFAULT_TENANT, rest
    else:
        tenant, _, secret = rest.rpartition(":") if ":" in rest else ("", "", rest)
        if tenant.endswith(":sha256"):                   # TENANT:sha256:HEX
            tenant, secret = tenant[:-len(":sha256")], f"sha256:{secret}"
        tenant = tenant if ":" in rest else DEFAULT_TENANT
    if ":" in tenant or not TENANT_PATTERN.fullmatch(tenant):
        raise ValueError("a token entry is TOKEN, TENANT:TOKEN or TENANT:TOKEN:admin, with a "
                         "tenant of 1-64 characters [A-Za-z0-9._-] (a token cannot contain ':')")
    if not secret:
        raise ValueError(f"a token entry of tenant {tenant!r} has an empty token")
    hashed = _DIGEST.fullmatch(secret)
    if secret.startswith("sha256:") and hashed is None:
        raise ValueError(f"a hashed token of tenant {tenant!r} must be sha256:<64 hex digits>")
    value = bytes.fromhex(hashed.group(1)) if hashed else digest(secret)
    return value, Principal(tenant, admin)


class TokenTable:
    """The configured tokens, as digests → principals (see the module docstring)."""

    def __init__(self, entries: Iterable[str]):
        self._entries = [_Entry(*parse_entry(e)) for e in entries]

    def __bool__(self) -> bool:
        return bool(self._entries)

    def __len__(self) -> int:
        return len(self._entries)

    def authenticate(self, token: str) -> Principal | None:
        """The principal of ``token``, or None; compares with every entry in constant time."""
        given = digest(token)
        found: Principal | None = None
        for entry in self._entries:              # no early exit: every digest is compared
            if hmac.compare_digest(given, entry.digest):
                found = entry.principal
        return found

    @property
    def tenants(self) -> Sequence[str]:
        return sorted({e.principal.tenant for e in self._entries})
