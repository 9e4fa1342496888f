"""Ids: prefixed lowercase ULIDs, and validation that keeps them safe as path components."""

from __future__ import annotations

import re
import time

import pytest

from models_store.errors import InvalidId
from models_store.ids import ALPHABET, PREFIXES, is_valid_id, new_id, validate_id


@pytest.mark.parametrize("kind", sorted(PREFIXES))
def test_new_id_is_prefix_and_26_crockford_characters(kind):
    value = new_id(kind)
    prefix, body = value.split("_")
    assert prefix == PREFIXES[kind]
    assert len(body) == 26 and set(body) <= set(ALPHABET)
    assert validate_id(kind, value) == value


def test_new_ids_are_unique_and_sort_by_creation_time():
    first = [new_id("job") for _ in range(1000)]
    assert len(set(first)) == 1000
    time.sleep(0.002)
    later = new_id("job")
    assert all(later > earlier for earlier in first)


def test_id_timestamp_is_the_current_millisecond():
    body = new_id("actor")[4:]
    millis = 0
    for char in body[:10]:
        millis = millis * 32 + ALPHABET.index(char)
    assert abs(millis - time.time() * 1000) < 5000


@pytest.mark.parametrize("value", [
    "../../etc/passwd",
    "act_../../../../etc/passwd",
    "act_/" + "0" * 25,
    "act_" + "0" * 25,                 # too short
    "act_" + "0" * 27,                 # too long
    "act_" + "0" * 25 + "I",           # upper case
    "act_" + "0" * 25 + "u",           # not Crockford
    "act_" + "0" * 26 + "\n",          # trailing newline
    " act_" + "0" * 26,
    "clp_" + "0" * 26,                 # another kind's prefix
    "act-" + "0" * 26,
    "",
    None,
    12345,
])
def test_validate_id_rejects_malformed_and_traversal(value):
    assert not is_valid_id("actor", value)
    with pytest.raises(InvalidId, match="not a valid actor id"):
        validate_id("actor", value)


def test_invalid_id_is_a_value_error_naming_the_value():
    with pytest.raises(ValueError, match=re.escape("'../x'")):
        validate_id("model", "../x")


def test_unknown_kind_is_a_key_error():
    with pytest.raises(KeyError, match="unknown id kind 'actress'"):
        new_id("actress")
