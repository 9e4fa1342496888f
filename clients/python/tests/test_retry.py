"""The retry policy, error mapping, auth and configuration, against fake servers
(``httpx.MockTransport``); backoff sleeps are recorded, never slept."""

from __future__ import annotations

import asyncio
import json

import httpx
import numpy as np
import pytest

from facesynth_client import (AsyncClient, BadRequest, Client, Conflict, NotFound, Overloaded,
                              ServerError, TransportError, Unprocessable)
from facesynth_client._core import parse_retry_after

PROBLEM = "application/problem+json"


def problem(status: int, detail: str, **headers: str) -> httpx.Response:
    return httpx.Response(status, headers={"content-type": PROBLEM, **headers}, content=json.dumps(
        {"type": "urn:facesynth:problem:x", "title": "T", "status": status,
         "detail": detail}).encode())


class Script:
    """A fake server answering each request with the next step: a response, or an
    exception class raised as the transport error."""

    def __init__(self, *steps):
        self.steps = list(steps)
        self.requests: list[httpx.Request] = []

    def __call__(self, request: httpx.Request) -> httpx.Response:
        self.requests.append(request)
        step = self.steps.pop(0) if len(self.steps) > 1 else self.steps[0]
        if isinstance(step, type) and issubclass(step, Exception):
            raise step("simulated", request=request)
        return step


def make(script, sleeps=None, **options) -> Client:
    return Client("http://fs.test", transport=httpx.MockTransport(script),
                  sleep=(sleeps.append if sleeps is not None else None),
                  random=lambda: 0.5, **options)


def test_connection_error_then_503_then_success_is_three_attempts():
    script = Script(httpx.ConnectError, problem(503, "busy", **{"Retry-After": "0"}),
                    httpx.Response(200, json={"status": "ok"}))
    sleeps: list[float] = []
    assert make(script, sleeps).health() == {"status": "ok"}
    assert len(script.requests) == 3
    assert sleeps == [0.25, 0.0]  # full jitter 0.5 · 0.5 · 2⁰, then Retry-After: 0


def test_post_is_retried_when_the_request_never_left_and_on_503():
    actor = {"id": "act_1", "name": "Ada", "metadata": {}, "created_at": "2025-01-15T09:30:00Z"}
    script = Script(httpx.ConnectError, problem(503, "busy", **{"Retry-After": "2"}),
                    httpx.Response(201, json=actor))
    sleeps: list[float] = []
    assert make(script, sleeps).actors.create("Ada").id == "act_1"
    assert [r.method for r in script.requests] == ["POST"] * 3
    assert all(json.loads(r.content) == {"name": "Ada"} for r in script.requests)
    assert sleeps == [0.25, 2.0]


def test_post_is_not_retried_after_a_read_timeout_but_get_is():
    script = Script(httpx.ReadTimeout)
    with pytest.raises(TransportError) as caught:
        make(script, []).actors.create("Ada")
    assert len(script.requests) == 1 and isinstance(caught.value.__cause__, httpx.ReadTimeout)

    script = Script(httpx.ReadTimeout, httpx.Response(200, json={"items": []}))
    assert make(script, []).actors.list() == []
    assert len(script.requests) == 2


@pytest.mark.parametrize("status, error", [(404, NotFound), (422, Unprocessable),
                                           (400, BadRequest), (409, Conflict),
                                           (500, ServerError)])
def test_other_errors_are_never_retried(status, error):
    script = Script(problem(status, "nope"))
    sleeps: list[float] = []
    with pytest.raises(error) as caught:
        make(script, sleeps).actors.get("act_1")
    assert len(script.requests) == 1 and sleeps == []
    assert caught.value.status == status and caught.value.detail == "nope"
    assert caught.value.problem["type"] == "urn:facesynth:problem:x"


def test_retries_are_bounded_and_backoff_grows_exponentially_with_a_cap():
    script = Script(httpx.ConnectError)
    sleeps: list[float] = []
    client = Client("http://fs.test", transport=httpx.MockTransport(script), sleep=sleeps.append,
                    random=lambda: 1.0, max_retries=4, backoff=0.5, backoff_max=3.0)
    with pytest.raises(TransportError):
        client.health()
    assert len(script.requests) == 5
    assert sleeps == [0.5, 1.0, 2.0, 3.0]


def test_exhausted_503_raises_overloaded_with_retry_after():
    script = Script(problem(503, "busy", **{"Retry-After": "1"}))
    sleeps: list[float] = []
    with pytest.raises(Overloaded) as caught:
        make(script, sleeps, max_retries=2).health()
    assert len(script.requests) == 3 and sleeps == [1.0, 1.0]
    assert caught.value.retry_after == 1.0


def test_no_retries_when_max_retries_is_zero():
    script = Script(httpx.ConnectError)
    with pytest.raises(TransportError):
        make(script, [], max_retries=0).health()
    assert len(script.requests) == 1


def test_full_jitter_stays_within_the_exponential_bound():
    client = Client("http://fs.test", transport=httpx.MockTransport(Script(httpx.ConnectError)))
    for attempt in range(6):
        bound = min(30.0, 0.5 * 2 ** attempt)
        assert all(0 <= client._core.backoff_delay(attempt) <= bound for _ in range(50))


def test_retry_after_as_seconds_or_http_date():
    assert parse_retry_after("3") == 3.0
    assert parse_retry_after("Wed, 21 Oct 2015 07:28:10 GMT", now=1445412480.0) == 10.0
    assert parse_retry_after("soon") is None and parse_retry_after(None) is None


def test_a_non_problem_error_body_still_maps_by_status():
    script = Script(httpx.Response(502, text="<html>bad gateway</html>"))
    with pytest.raises(ServerError) as caught:
        make(script, []).health()
    assert caught.value.status == 502 and "bad gateway" in caught.value.detail


def test_async_client_shares_the_retry_policy():
    script = Script(httpx.ConnectError, problem(503, "busy", **{"Retry-After": "0"}),
                    httpx.Response(200, json={"status": "ok"}))
    sleeps: list[float] = []

    async def main():
        async with AsyncClient("http://fs.test", transport=httpx.MockTransport(script),
                               sleep=sleeps.append, random=lambda: 0.5) as fs:
            return await fs.health()

    assert asyncio.run(main()) == {"status": "ok"}
    assert len(script.requests) == 3 and sleeps == [0.25, 0.0]


def test_bearer_token_and_base_url_from_arguments_or_environment(monkeypatch):
    seen = []

    def handler(request):
        seen.append(request)
        return httpx.Response(200, json={"status": "ok"})

    Client("http://a.test/", token="s3cret", transport=httpx.MockTransport(handler)).health()
    assert str(seen[-1].url) == "http://a.test/healthz"
    assert seen[-1].headers["authorization"] == "Bearer s3cret"

    monkeypatch.setenv("FACESYNTH_URL", "http://env.test:9000")
    monkeypatch.setenv("FACESYNTH_TOKEN", "from-env")
    client = Client(transport=httpx.MockTransport(handler))
    client.health()
    assert client.base_url == "http://env.test:9000"
    assert str(seen[-1].url) == "http://env.test:9000/healthz"
    assert seen[-1].headers["authorization"] == "Bearer from-env"

    monkeypatch.delenv("FACESYNTH_URL")
    monkeypatch.delenv("FACESYNTH_TOKEN")
    client = Client(transport=httpx.MockTransport(handler))
    client.health()
    assert client.base_url == "http://127.0.0.1:8000"
    assert "authorization" not in seen[-1].headers

    injected = httpx.Client(base_url="http://injected.test", transport=httpx.MockTransport(handler))
    Client(http_client=injected).health()
    assert str(seen[-1].url) == "http://injected.test/healthz"


def test_timeouts_are_configurable():
    seen = []

    def handler(request):
        seen.append(request.extensions["timeout"])
        return httpx.Response(200, json={"status": "ok"})

    Client("http://a.test", timeout=7.5, transport=httpx.MockTransport(handler)).health()
    assert seen[-1]["read"] == 7.5 and seen[-1]["connect"] == 7.5
    Client("http://a.test", timeout=httpx.Timeout(5.0, connect=1.0),
           transport=httpx.MockTransport(handler)).health()
    assert seen[-1]["read"] == 5.0 and seen[-1]["connect"] == 1.0


def test_synthesize_sends_npz_or_json_with_nulls_for_occluded_markers():
    bodies = []
    out = io_npz(vertices=np.zeros((2, 5, 3), np.float32))

    def handler(request):
        bodies.append(request)
        return httpx.Response(200, content=out, headers={"content-type": "application/x-npz"})

    client = Client("http://a.test", transport=httpx.MockTransport(handler))
    markers = np.arange(12, dtype=float).reshape(2, 2, 3)
    markers[1, 0] = np.nan
    result = client.synthesize("mdl_1", markers, outputs=["mesh", "albedo"])
    assert result["vertices"].shape == (2, 5, 3)
    request = bodies[-1]
    assert request.headers["content-type"] == "application/x-npz"
    assert request.url.params["outputs"] == "mesh,albedo"
    from facesynth_client import load_npz
    np.testing.assert_array_equal(load_npz(request.content)["markers"], markers)

    client.synthesize("mdl_1", markers, map_resolution=64)
    body = json.loads(bodies[-1].content)
    assert body["markers"][1][0] is None and body["markers"][0][1] == [3.0, 4.0, 5.0]
    assert body["map_resolution"] == 64


def io_npz(**arrays) -> bytes:
    from facesynth_client import npz_bytes
    return npz_bytes(**arrays)


def test_npz_encoding_refuses_object_arrays_and_decoding_refuses_pickles():
    from facesynth_client import load_npz, npz_bytes
    with pytest.raises(TypeError):
        npz_bytes(bad=np.array([object()], dtype=object))
    import io as _io
    buffer = _io.BytesIO()
    np.savez(buffer, bad=np.array([{"a": 1}], dtype=object))
    with pytest.raises(ValueError):
        load_npz(buffer.getvalue())


def test_tracking_job_is_sent_as_multipart_with_json_params():
    seen = []

    def handler(request):
        seen.append(request)
        return httpx.Response(202, json={"job_id": "job_9"}, headers={"location": "/v1/jobs/job_9"})

    client = Client("http://a.test", transport=httpx.MockTransport(handler))
    accepted = client.tracking.submit("act_1", {"scans": [b"PK-scan-0", b"PK-scan-1"],
                                                "cameras": ("cams.json", b"{}", "application/json")},
                                      params={"iterations": 3})
    assert accepted.job_id == "job_9" and accepted.location == "/v1/jobs/job_9"
    request = seen[-1]
    assert request.url.path == "/v1/actors/act_1/tracking-jobs"
    body = request.content
    assert request.headers["content-type"].startswith("multipart/form-data")
    assert body.count(b'form-data; name="scans"') == 2 and b'filename="cams.json"' in body
    assert b'name="params"' in body and b'{"iterations": 3}' in body


def test_mesh_uploads_from_trimesh_like_objects_keep_order_and_send_int32_faces():
    from types import SimpleNamespace

    from facesynth_client import load_npz

    seen = []

    def handler(request):
        seen.append(request)
        return httpx.Response(200, json={"vertex_count": 3, "triangle_count": 1, "uv_seams": 0})

    V = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]], np.float32)
    mesh = SimpleNamespace(vertices=V, faces=np.array([[0, 1, 2]], np.int64),
                           visual=SimpleNamespace(uv=np.array([[0, 0], [1, 0], [0, 1]], float)))
    Client("http://a.test", transport=httpx.MockTransport(handler)).actors.upload_neutral(
        "act_1", mesh)
    arrays = load_npz(seen[-1].content)
    assert seen[-1].headers["content-type"] == "application/x-npz"
    np.testing.assert_array_equal(arrays["vertices"], V)
    assert arrays["faces"].dtype == np.int32 and arrays["uv"].shape == (3, 2)


def test_a_broken_event_stream_is_a_transport_error_for_iterators():
    class Broken(httpx.SyncByteStream):
        def __iter__(self):
            yield b'event: progress\ndata: {"id": "job_1", "kind": "k", "status": "running", "progress": 0.1, "stage": ""}\n\n'
            raise httpx.ReadError("reset")

    client = Client("http://a.test", transport=httpx.MockTransport(
        lambda request: httpx.Response(200, stream=Broken(),
                                       headers={"content-type": "text/event-stream"})))
    states = []
    with pytest.raises(TransportError):
        for state in client.jobs.events("job_1"):
            states.append(state)
    assert [s.progress for s in states] == [0.1]
