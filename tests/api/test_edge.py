"""service.api.edge: what is refused before any route runs (issue 16, defect 7) and how a
500 ends (defect 8)."""

from __future__ import annotations

import logging

import pytest

from tests.api.conftest import NPZ, assert_problem


@pytest.mark.parametrize("url", [
    "/v1/jobs?kind=%00", "/v1/jobs?actor_id=%00", "/v1/jobs?status=queued%00",
    "/v1/jobs?kind=%ff%fe", "/v1/actors/act_%00", "/v1/jobs?%00=1",
])
def test_nul_bytes_and_invalid_utf8_in_the_url_are_422(client, url):
    body = assert_problem(client.get(url), 422)
    assert "NUL" in body["detail"] or "UTF-8" in body["detail"]


def test_a_clip_upload_with_nul_in_its_name_is_422(client, actor_id):
    assert_problem(client.post(f"/v1/actors/{actor_id}/clips?name=a%00b", content=b"x",
                               headers=NPZ), 422, "NUL")


def test_ordinary_escapes_pass(client):
    assert client.get("/v1/jobs?kind=train%20x").status_code == 200
