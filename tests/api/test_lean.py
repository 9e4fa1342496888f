"""The lean ASGI path of ``POST /v1/models/{id}/synthesize`` (service/api/lean.py): for every
request, the same status, headers and body bytes as FastAPI's route (an app with
``lean_synthesis=False`` on the same services), and FastAPI's route handler left unrun
exactly when the lean path served the request."""

from __future__ import annotations

import errno
import inspect

import numpy as np
import pytest
from fastapi.testclient import TestClient
from pydantic import TypeAdapter

from models_store import registry
from service.api import create_app
from service.api.auth import check_bearer
from service.api.errors import Unauthorized
from service.api.lean import FLAG_DEFAULTS, FLAGS, plain_query, synthesize_route
from service.api.query import declared_query
from service.api.routes import synthesis
from service.app import operations
from service.app.services import Services
from service.config import Settings
from service.errors import Corrupt, Unavailable
from starlette.datastructures import QueryParams
from starlette.requests import Request
from tests.api.conftest import NPZ, Recorder, make_client, npz, upload_sample_actor
from tests.conftest import PDM_TRAINING

#: the request id every compared request sends, so problem bodies and headers compare
REQUEST_ID = {"X-Request-ID": "lean-compare"}
MAX_BODY = 8 << 20


class FastApiCalls:
    """Counts the runs of FastAPI's handler of the synthesize route (the lean path never
    runs it)."""

    def __init__(self, monkeypatch):
        self.count = 0
        route = synthesize_route()
        handle = route.handle

        async def counting(scope, receive, send):
            self.count += 1
            await handle(scope, receive, send)
        monkeypatch.setattr(route, "handle", counting)


@pytest.fixture(scope="module")
def pair(tmp_path_factory, pdm_actor_dir, pdm_model):
    """(lean client, FastAPI client, ready model id, queued model id, heldout markers
    (2,M,3)): two apps on the same services, one with the lean path."""
    tmp = tmp_path_factory.mktemp("api_lean")
    settings = Settings(data_dir=tmp / "data", max_frames_per_request=4, max_map_resolution=256,
                        max_body_bytes=MAX_BODY, synthesis_queue_seconds=0.0, tokens=[])
    with make_client(settings, Recorder()) as lean:
        actor_id, clip_ids = upload_sample_actor(lean, pdm_actor_dir, PDM_TRAINING[:1])
        ids = [lean.post(f"/v1/actors/{actor_id}/models", json={
            "kind": "pdm", "clips": [clip_ids[PDM_TRAINING[0]]]}).json()["model_id"]
            for _ in range(2)]
        pdm_model.save(tmp / "model")
        services = lean.app.state.services
        with services.session() as session:
            registry.mark_model_ready(session, services.blobs, ids[0], tmp / "model",
                                      metrics=pdm_model.metrics)
        with np.load(pdm_actor_dir / "performances" / "heldout_in_range.npz") as d:
            markers = d["markers"][:2].astype(np.float64)
        plain = create_app(settings.model_copy(update={"lean_synthesis": False}),
                           services=services)
        with TestClient(plain) as fastapi:
            yield lean, fastapi, ids[0], ids[1], markers


def _cases(markers: np.ndarray) -> list[tuple[str, dict, str, int]]:
    """(name, request keywords (``model``: the model id to use), who answers, status) per
    case; who: ``lean``, ``fastapi`` (a query string that is not plain) or ``edge`` (a
    middleware, before any route)."""
    body = npz(markers=markers)
    one = npz(markers=markers[:1])
    bad = markers.copy()
    bad[1, 2, 0] = np.inf
    json_type = {"Content-Type": "application/json"}
    return [
        ("default outputs", dict(content=body, headers=NPZ), "lean", 200),
        ("mesh, half, no faces", dict(content=one, headers=NPZ, params={
            "outputs": "mesh", "half": "true", "topology": "false"}), "lean", 200),
        ("maps half", dict(content=one, headers=NPZ, params={
            "outputs": "mesh,displacement,normal_map", "half": "1"}), "lean", 200),
        ("outputs repeated, clamp off", dict(content=body, headers=NPZ, params=[
            ("outputs", "mesh"), ("outputs", "albedo"), ("clamp", "0")]), "lean", 200),
        ("obj", dict(content=one, headers={**NPZ, "Accept": "model/obj"}), "lean", 200),
        ("exr", dict(content=one, headers={**NPZ, "Accept": "image/x-exr"},
                     params={"outputs": "displacement"}), "lean", 200),
        ("json body", dict(json={"markers": markers[:1].tolist(), "map_resolution": 64},
                           params={"outputs": "mesh,albedo"}), "lean", 200),
        ("wrong marker count", dict(content=npz(markers=markers[:, :-1]), headers=NPZ),
         "lean", 422),
        ("too many frames", dict(content=npz(markers=np.repeat(markers, 3, axis=0)),
                                 headers=NPZ), "lean", 413),
        ("not finite", dict(content=npz(markers=bad), headers=NPZ), "lean", 422),
        ("unknown output", dict(content=body, headers=NPZ, params={"outputs": "wrinkles"}),
         "lean", 422),
        ("obj of two frames", dict(content=body, headers={**NPZ, "Accept": "model/obj"}),
         "lean", 422),
        ("exr of two maps", dict(content=one, headers={**NPZ, "Accept": "image/x-exr"}),
         "lean", 422),
        ("not acceptable", dict(content=body, headers={**NPZ, "Accept": "text/html"}),
         "lean", 406),
        ("no markers array", dict(content=npz(vertices=markers), headers=NPZ), "lean", 422),
        ("json without markers", dict(content=b"{}", headers=json_type), "lean", 422),
        ("broken json", dict(content=b"{", headers=json_type), "lean", 400),
        ("unsupported media type", dict(content=b"x", headers={"Content-Type": "text/csv"}),
         "lean", 415),
        ("no content type", dict(content=body), "lean", 415),
        ("Accept given twice", dict(content=one, headers=[
            ("Content-Type", "application/x-npz"), ("Accept", "model/obj"),
            ("Accept", "application/x-npz")]), "lean", 200),
        ("empty body", dict(content=b"", headers=NPZ), "lean", 400),
        ("map resolution over the limit", dict(json={"markers": markers[:1].tolist(),
                                                     "map_resolution": 512}), "lean", 413),
        ("body over max_body_bytes", dict(content=b"\0" * (MAX_BODY + 1), headers=NPZ),
         "edge", 413),
        ("streamed body over max_body_bytes", dict(
            content=lambda: iter([b"\0" * (MAX_BODY // 2 + 1)] * 2), headers=NPZ), "lean", 413),
        ("unknown model", dict(model="mdl_" + "0" * 26, content=body, headers=NPZ),
         "lean", 404),
        ("invalid model id", dict(model="nope", content=body, headers=NPZ), "lean", 404),
        ("model not ready", dict(model="queued", content=body, headers=NPZ), "lean", 409),
        # not plain: FastAPI answers on both apps
        ("misspelt parameter", dict(content=body, headers=NPZ, params={"outptus": "mesh"}),
         "fastapi", 422),
        ("flag not a boolean", dict(content=body, headers=NPZ, params={"half": "maybe"}),
         "fastapi", 422),
        ("flag spelt yes", dict(content=one, headers=NPZ, params={
            "half": "yes", "outputs": "mesh"}), "fastapi", 200),
        ("flag repeated", dict(content=one, headers=NPZ, params=[
            ("outputs", "mesh"), ("topology", "true"), ("topology", "false")]), "fastapi", 200),
        ("flag empty", dict(content=one, headers=NPZ, params={"clamp": ""}), "fastapi", 422),
        ("NUL in the query", dict(content=body, headers=NPZ, params={"outputs": "mesh\0"}),
         "edge", 422),
    ]


CASES = [name for name, *_ in _cases(np.zeros((2, 3, 3)))]


def _send(client, model_id: str, queued: str, request: dict):
    request = dict(request)
    model = request.pop("model", model_id)
    model = queued if model == "queued" else model
    headers = request.pop("headers", {})
    headers = [*REQUEST_ID.items(), *(headers if isinstance(headers, list) else headers.items())]
    if callable(request.get("content")):      # a chunked body, made anew for each send
        request["content"] = request["content"]()
    return client.post(f"/v1/models/{model}/synthesize", headers=headers, **request)


@pytest.mark.parametrize("case", CASES)
def test_lean_path_answers_byte_for_byte_what_fastapi_answers(pair, monkeypatch, case):
    lean, fastapi, model_id, queued, markers = pair
    _, request, who, status = next(c for c in _cases(markers) if c[0] == case)
    calls = FastApiCalls(monkeypatch)
    expected = _send(fastapi, model_id, queued, request)
    # FastAPI routes the path to this very route object (unless a middleware answered)
    assert calls.count == (0 if who == "edge" else 1)
    got = _send(lean, model_id, queued, request)
    assert calls.count == {"edge": 0, "lean": 1, "fastapi": 2}[who]
    assert got.status_code == expected.status_code == status, got.text
    assert got.headers.multi_items() == expected.headers.multi_items()
    assert got.content == expected.content


def test_other_methods_on_the_route_are_fastapis_405(pair, monkeypatch):
    lean, fastapi, model_id, _, _ = pair
    got, expected = (c.get(f"/v1/models/{model_id}/synthesize", headers=REQUEST_ID)
                     for c in (lean, fastapi))
    assert got.status_code == expected.status_code == 405
    assert got.headers.multi_items() == expected.headers.multi_items()
    assert got.content == expected.content


def test_a_busy_synthesis_is_the_same_503_with_retry_after(pair):
    lean, fastapi, model_id, queued, markers = pair
    answers = []
    for client in (fastapi, lean):
        slots = client.app.state.synthesizer.pool
        held = [slots.acquire(blocking=False) for _ in range(client.app.state.synthesizer.limit)]
        try:
            answers.append(_send(client, model_id, queued,
                                 dict(content=npz(markers=markers), headers=NPZ)))
        finally:
            for ok in held:
                if ok:
                    slots.release()
    expected, got = answers
    assert got.status_code == expected.status_code == 503
    assert got.headers["retry-after"] == expected.headers["retry-after"]
    assert got.headers.multi_items() == expected.headers.multi_items()
    assert got.content == expected.content


@pytest.mark.parametrize("error, status", [
    (RuntimeError("a bug"), 500), (OSError(errno.ENOSPC, "No space left on device"), 507),
    (OSError(errno.EROFS, "Read-only file system"), 503), (Corrupt("checksum"), 500),
    (Unavailable("busy", retry_after=3), 503)])
def test_errors_of_the_synthesis_map_to_the_same_answers(pair, monkeypatch, error, status):
    lean, fastapi, model_id, queued, markers = pair

    def fail(*args, **kwargs):
        raise error
    monkeypatch.setattr(operations, "synthesize", fail)
    request = dict(content=npz(markers=markers), headers=NPZ)
    expected, got = (_send(c, model_id, queued, request) for c in (fastapi, lean))
    assert got.status_code == expected.status_code == status
    assert got.headers.multi_items() == expected.headers.multi_items()
    assert got.content == expected.content


def test_lean_requests_are_timed_under_the_route_template(pair):
    lean, _, model_id, queued, markers = pair
    _send(lean, model_id, queued, dict(content=npz(markers=markers[:1]), headers=NPZ,
                                       params={"outputs": "mesh"}))
    _send(lean, model_id, queued, dict(content=b"x", headers={"Content-Type": "text/csv"}))
    text = lean.get("/metrics").text
    for status in (200, 415):
        assert (f'facesynth_http_request_duration_seconds_count{{method="POST",'
                f'route="/v1/models/{{model_id}}/synthesize",status="{status}"}}') in text


def test_an_override_of_a_route_dependency_leaves_the_request_to_fastapi(pair, monkeypatch):
    lean, _, model_id, queued, markers = pair
    calls = FastApiCalls(monkeypatch)

    async def refuse(request: Request) -> None:
        raise Unauthorized("overridden")
    monkeypatch.setitem(lean.app.dependency_overrides, check_bearer, refuse)
    got = _send(lean, model_id, queued, dict(content=npz(markers=markers), headers=NPZ))
    assert got.status_code == 401 and got.json()["detail"] == "overridden"
    assert calls.count == 1


TENANT_TOKENS = ["default:token-d", "studio-b:token-b"]


@pytest.mark.parametrize("token", [None, "wrong", "token-b", "token-d"])
def test_tokens_and_tenants_answer_as_fastapi(pair, token):
    """With tokens configured: no or a wrong token 401, another tenant's token 404 (the
    model is not its), the model's tenant 200 — on both paths, byte for byte."""
    lean, _, model_id, queued, markers = pair
    settings = lean.app.state.services.settings.model_copy(update={"tokens": TENANT_TOKENS})
    services = Services.open(settings)
    try:
        answers = []
        for flag in (False, True):
            app = create_app(settings.model_copy(update={"lean_synthesis": flag}),
                             services=services)
            with TestClient(app) as client:
                headers = {**NPZ, **({"Authorization": f"Bearer {token}"} if token else {})}
                answers.append(_send(client, model_id, queued, dict(
                    content=npz(markers=markers[:1]), headers=headers,
                    params={"outputs": "mesh"})))
    finally:
        services.close()
    expected, got = answers
    assert got.status_code == expected.status_code == {
        None: 401, "wrong": 401, "token-b": 404, "token-d": 200}[token]
    assert got.headers.multi_items() == expected.headers.multi_items()
    assert got.content == expected.content


def test_flags_are_read_as_pydantic_reads_them_and_match_the_endpoint():
    adapter = TypeAdapter(bool)
    assert all(adapter.validate_python(text) is value for text, value in FLAGS.items())
    signature = inspect.signature(synthesis.synthesize).parameters
    assert {name: signature[name].default for name in FLAG_DEFAULTS} == FLAG_DEFAULTS
    assert declared_query(synthesize_route()) == {"outputs", *FLAG_DEFAULTS}


@pytest.mark.parametrize("query, expected", [
    (b"", {"outputs": None, "clamp": True, "half": False, "topology": True}),
    (b"outputs=mesh,albedo&outputs=displacement&half=1&clamp=false&topology=0",
     {"outputs": ["mesh,albedo", "displacement"], "clamp": False, "half": True,
      "topology": False}),
    (b"outputs=", {"outputs": [""], "clamp": True, "half": False, "topology": True}),
    (b"half=True", None), (b"half=", None), (b"half=1&half=1", None), (b"Half=1", None),
    (b"outputs=mesh&x=1", None), (b"=1", None),
])
def test_plain_query(query, expected):
    known = declared_query(synthesize_route())
    assert plain_query(QueryParams(query), known) == expected
