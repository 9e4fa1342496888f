"""models_store.tenancy: token entries, hashed tokens, constant-time lookup (issue 16, defect 13)."""

from __future__ import annotations

import hashlib

import pytest

from models_store.tenancy import ANONYMOUS, Principal, TokenTable, parse_entry


def sha(token: str) -> str:
    return "sha256:" + hashlib.sha256(token.encode()).hexdigest()


def test_entries_map_tokens_to_tenants_and_admins():
    table = TokenTable(["plain", "studio-a:alpha", "studio-b:beta:admin", sha("hashed"),
                        f"studio-c:{sha('gamma')}", f"ops:{sha('root')}:admin"])
    assert table.authenticate("plain") == Principal("default")
    assert table.authenticate("alpha") == Principal("studio-a")
    assert table.authenticate("beta") == Principal("studio-b", admin=True)
    assert table.authenticate("hashed") == Principal("default")
    assert table.authenticate("gamma") == Principal("studio-c")
    assert table.authenticate("root") == Principal("ops", admin=True)
    for wrong in ("", "alph", "alpha ", "studio-a:alpha", sha("gamma"), "ALPHA"):
        assert table.authenticate(wrong) is None
    assert table.tenants == ["default", "ops", "studio-a", "studio-b", "studio-c"]
    assert Principal("studio-a").scope == "studio-a" and ANONYMOUS.scope is None


def test_plaintext_tokens_are_not_kept():
    table = TokenTable(["studio-a:s3cret-token"])
    assert "s3cret-token" not in repr(vars(table)) and b"s3cret-token" not in repr(vars(table)).encode()


@pytest.mark.parametrize("entry", ["bad tenant:tok", "a:b:c", "studio:", ":tok",
                                   "studio:sha256:abc", "../x:tok", "x" * 65 + ":tok"])
def test_malformed_entries_are_refused_without_showing_the_token(entry):
    with pytest.raises(ValueError) as raised:
        parse_entry(entry)
    secret = entry.rsplit(":", 1)[-1]
    assert len(secret) < 4 or secret not in str(raised.value)


def test_a_bad_token_setting_does_not_echo_the_tokens():
    from service.config import Settings

    with pytest.raises(ValueError) as raised:
        Settings(tokens=["studio-a:good-secret", "bad tenant:supersecret"])
    assert "token entry 2" in str(raised.value)
    assert "supersecret" not in str(raised.value) and "good-secret" not in str(raised.value)
