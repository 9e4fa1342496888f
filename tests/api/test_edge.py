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


# -- a 500 closes the connection and logs the right request id (defect 8) --------------------
def test_a_500_says_connection_close_and_logs_its_request_id(client, caplog):
    from service.logs import request_id_var

    def boom():
        raise RuntimeError("kaboom")

    client.app.add_api_route("/v1/boom", boom, methods=["GET"])
    logged = []

    class Grab(logging.Handler):
        def emit(self, record):
            if record.exc_info:
                logged.append(request_id_var.get())

    handler = Grab()
    logging.getLogger().addHandler(handler)
    try:
        client.get("/v1/jobs", headers={"X-Request-ID": "earlier-request"})
        response = client.get("/v1/boom", headers={"X-Request-ID": "req-boom-1"})
    finally:
        logging.getLogger().removeHandler(handler)
    body = assert_problem(response, 500, "request id")
    assert body["request_id"] == "req-boom-1" == response.headers["x-request-id"]
    assert response.headers["connection"] == "close"
    assert "kaboom" not in response.text
    assert logged == ["req-boom-1"]
    # the client's next request on a new connection works
    assert client.get("/v1/jobs").status_code == 200
