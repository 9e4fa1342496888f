"""Health, readiness, metrics, request ids, bearer auth and the body-size limit."""

from __future__ import annotations

import json
import logging

import pytest

from service.api.auth import token_matches
from service.config import Settings
from tests.api.conftest import Recorder, assert_problem, make_client


def test_healthz_and_readyz(client):
    assert client.get("/healthz").json() == {"status": "ok"}
    ready = client.get("/readyz")
    assert ready.status_code == 200, ready.text
    assert ready.json()["checks"] == {"database": "ok", "blobs": "ok", "queue": "ok"}


def test_readyz_names_what_is_unreachable(client, monkeypatch):
    services = client.app.state.services
    monkeypatch.setattr(services, "check", lambda: {"database": "ok", "blobs": "ok",
                                                    "queue": "unreachable: ConnectionError"})
    response = client.get("/readyz")
    assert response.status_code == 503 and response.json()["status"] == "unavailable"


def test_metrics_expose_latency_queue_depth_and_jobs(client, actor_id):
    client.get(f"/v1/actors/{actor_id}")
    text = client.get("/metrics").text
    assert ('facesynth_http_request_duration_seconds_count{method="GET",'
            'route="/v1/actors/{actor_id}",status="200"} 1.0') in text
    assert "facesynth_jobs_queued 0.0" in text
    assert "# TYPE facesynth_job_duration_seconds histogram" in text
    assert "# TYPE facesynth_synthesis_frames_total counter" in text


def test_request_id_is_echoed_or_made(client, caplog):
    with caplog.at_level(logging.INFO, logger="facesynth.access"):
        response = client.get("/healthz", headers={"X-Request-ID": "trace-42"})
    assert response.headers["x-request-id"] == "trace-42"
    record = next(r for r in caplog.records if r.name == "facesynth.access")
    assert record.status == 200 and record.route == "/healthz"
    made = client.get("/healthz", headers={"X-Request-ID": "bad id\x01"}).headers["x-request-id"]
    assert made != "bad id\x01" and len(made) == 32
    problem = client.get("/v1/actors/act_x", headers={"X-Request-ID": "abc"}).json()
    assert problem["request_id"] == "abc"


def test_json_log_lines_carry_the_request_id():
    from service.logs import JsonFormatter, request_id_var

    token = request_id_var.set("rid-1")
    try:
        record = logging.makeLogRecord({"name": "x", "msg": "hello %s", "args": ("you",),
                                        "levelname": "INFO", "status": 201})
        line = json.loads(JsonFormatter().format(record))
    finally:
        request_id_var.reset(token)
    assert line["message"] == "hello you" and line["request_id"] == "rid-1"
    assert line["status"] == 201 and line["level"] == "info"


def test_unknown_route_and_method_are_problems(client):
    assert_problem(client.get("/v2/nothing"), 404)
    assert_problem(client.put("/healthz"), 405)


def test_body_over_the_limit_is_413_naming_it(client, actor_id, settings):
    url = f"/v1/actors/{actor_id}/neutral"
    big = b"x" * (settings.max_body_bytes + 1)
    assert_problem(client.put(url, content=big, headers={"Content-Type": "application/x-npz"}),
                   413, f"limit of {settings.max_body_bytes} bytes")

    def chunks():                       # no Content-Length: counted while streaming
        for _ in range(settings.max_body_bytes // (1 << 20) + 2):
            yield b"x" * (1 << 20)

    assert_problem(client.put(url, content=chunks(), headers={"Content-Type": "application/x-npz"}),
                   413, f"limit of {settings.max_body_bytes} bytes")
    assert_problem(client.post("/v1/actors", content=chunks(),
                               headers={"Content-Type": "application/json"}), 413)


@pytest.fixture
def secured(tmp_path):
    with make_client(Settings(data_dir=tmp_path, tokens=["s3cret", "other"]), Recorder()) as c:
        yield c


def test_bearer_tokens_are_required_when_configured(secured):
    response = secured.get("/v1/actors")
    assert_problem(response, 401, "Authorization: Bearer")
    assert response.headers["www-authenticate"].startswith("Bearer")
    assert_problem(secured.get("/v1/actors", headers={"Authorization": "Bearer wrong"}), 401,
                   "not valid")
    assert_problem(secured.get("/v1/actors", headers={"Authorization": "Basic s3cret"}), 401)
    assert secured.get("/v1/actors", headers={"Authorization": "Bearer other"}).status_code == 200
    assert secured.get("/healthz").status_code == 200
    assert secured.get("/metrics").status_code == 200


def test_token_matches_every_token():
    assert token_matches("b", ["a", "b"]) and not token_matches("c", ["a", "b"])
    assert not token_matches("", ["a"])


# -- tenants (issue 16, defect 13) -----------------------------------------------------------
TENANT_TOKENS = ["studio-a:token-a", "studio-b:sha256:"
                 + __import__("hashlib").sha256(b"token-b").hexdigest(), "ops:token-ops:admin"]


def bearer(token: str) -> dict[str, str]:
    return {"Authorization": f"Bearer {token}"}


def test_tokens_map_to_tenants_and_other_tenants_ids_are_unknown(tmp_path):
    with make_client(Settings(data_dir=tmp_path, tokens=TENANT_TOKENS), Recorder()) as c:
        a = c.post("/v1/actors", json={"name": "A"}, headers=bearer("token-a")).json()["id"]
        b = c.post("/v1/actors", json={"name": "B"}, headers=bearer("token-b")).json()["id"]
        assert [x["id"] for x in c.get("/v1/actors", headers=bearer("token-a")).json()["items"]] == [a]
        assert [x["id"] for x in c.get("/v1/actors", headers=bearer("token-b")).json()["items"]] == [b]
        both = c.get("/v1/actors", headers=bearer("token-ops")).json()["items"]
        assert {x["id"] for x in both} == {a, b}
        unknown = "act_" + "0" * 26
        for method in ("GET", "DELETE"):
            crossed = c.request(method, f"/v1/actors/{a}", headers=bearer("token-b"))
            twin = c.request(method, f"/v1/actors/{unknown}", headers=bearer("token-b"))
            assert crossed.status_code == twin.status_code == 404
            assert crossed.json()["detail"].replace(a, unknown) == twin.json()["detail"]
        assert c.get(f"/v1/actors/{a}", headers=bearer("token-a")).status_code == 200
        assert c.get(f"/v1/actors/{a}", headers=bearer("token-ops")).status_code == 200
        assert c.get("/v1/jobs", headers=bearer("token-b")).json()["items"] == []


def test_health_metrics_and_docs_can_require_a_token(tmp_path):
    settings = Settings(data_dir=tmp_path, tokens=["t"], public_health=False,
                        public_metrics=False, public_docs=False)
    with make_client(settings, Recorder()) as c:
        for path in ("/healthz", "/readyz", "/metrics", "/openapi.json", "/docs"):
            assert c.get(path).status_code == 401, path
            assert c.get(path, headers=bearer("t")).status_code == 200, path
    with make_client(Settings(data_dir=tmp_path / "open", tokens=["t"]), Recorder()) as c:
        for path in ("/healthz", "/readyz", "/metrics", "/openapi.json", "/docs"):
            assert c.get(path).status_code == 200, path
