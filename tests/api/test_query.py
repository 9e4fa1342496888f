"""service/api/query.py: unknown query parameters are a 422 naming them, and every list
route pages with ``limit`` / ``cursor`` / ``next_cursor``."""

from __future__ import annotations

import pytest

from service.api.query import encode_cursor
from tests.api.conftest import assert_problem

LIST_ROUTES = ["/v1/actors", "/v1/actors/{actor_id}/clips", "/v1/actors/{actor_id}/input-rigs",
               "/v1/actors/{actor_id}/models", "/v1/models/{model_id}/maps", "/v1/kinds",
               "/v1/jobs", "/v1/jobs/{job_id}/artifacts"]


def test_a_misspelt_query_parameter_is_a_422_naming_it(client):
    response = client.post("/v1/models/mdl_01jb3k9w2d5f7h3k6m8p0r2tvb/synthesize",
                           params={"outptus": "mesh"}, json={"markers": []})
    body = assert_problem(response, 422, "query.outptus", "unknown query parameter 'outptus'")
    assert body["errors"] == [{"loc": ["query", "outptus"], "type": "extra_forbidden",
                               "msg": body["errors"][0]["msg"]}]


def test_declared_parameters_pass_and_every_unknown_one_is_listed(client):
    assert client.get("/v1/jobs", params={"status": "queued", "limit": 5}).status_code == 200
    body = assert_problem(client.get("/v1/jobs", params={"stauts": "queued", "x": "1"}), 422)
    assert [e["loc"] for e in body["errors"]] == [["query", "stauts"], ["query", "x"]]
    assert "status" in body["errors"][0]["msg"]  # names what the route does take
    # unauthenticated routes are checked too; /docs (not an API route) is not
    assert_problem(client.get("/healthz", params={"verbose": "1"}), 422, "verbose")


def test_actors_page_by_cursor_without_skipping_or_repeating(client):
    ids = [client.post("/v1/actors", json={"name": f"a{k}"}).json()["id"] for k in range(5)]
    pages, cursor = [], None
    while True:
        body = client.get("/v1/actors", params={"limit": 2, **({"cursor": cursor} if cursor else {})}).json()
        pages.append([a["id"] for a in body["items"]])
        cursor = body["next_cursor"]
        if cursor is None:
            break
    assert pages == [ids[0:2], ids[2:4], ids[4:5]]
    # a deleted last item still marks its place (keyset, not offset)
    first = client.get("/v1/actors", params={"limit": 2}).json()
    assert client.delete(f"/v1/actors/{ids[1]}").status_code == 204
    rest = client.get("/v1/actors", params={"limit": 10, "cursor": first["next_cursor"]}).json()
    assert [a["id"] for a in rest["items"]] == ids[2:] and rest["next_cursor"] is None
    # without limit: the default page holds them all, and says there is no more
    assert len(client.get("/v1/actors").json()["items"]) == 4


def test_in_memory_listing_pages_in_its_own_order(client):
    everything = [k["name"] for k in client.get("/v1/kinds").json()["items"]]
    assert len(everything) >= 2
    seen, cursor = [], None
    while True:
        body = client.get("/v1/kinds", params={"limit": 1, **({"cursor": cursor} if cursor else {})}).json()
        assert len(body["items"]) == 1
        seen += [k["name"] for k in body["items"]]
        cursor = body["next_cursor"]
        if cursor is None:
            break
    assert seen == everything


@pytest.mark.parametrize("params, where", [
    ({"limit": 0}, "query.limit"), ({"limit": 1001}, "query.limit"),
    ({"cursor": "%%%"}, "query.cursor"), ({"cursor": encode_cursor(["x"])}, "query.cursor"),
    ({"cursor": encode_cursor(["2025-01-01T00:00:00", "act_x"])}, "query.cursor")])
def test_bad_limits_and_cursors_are_422s(client, params, where):
    assert_problem(client.get("/v1/actors", params=params), 422, where)


def test_openapi_documents_paging_on_every_list_route(client):
    paths = client.get("/openapi.json").json()["paths"]
    for route in LIST_ROUTES:
        get = paths[route]["get"]
        names = {p["name"] for p in get["parameters"] if p["in"] == "query"}
        assert {"limit", "cursor"} <= names, route
        ref = get["responses"]["200"]["content"]["application/json"]["schema"]["$ref"]
        schema = client.get("/openapi.json").json()["components"]["schemas"][ref.split("/")[-1]]
        assert "next_cursor" in schema["properties"], route
    description = client.get("/openapi.json").json()["info"]["description"]
    assert "extra_forbidden" in description and "next_cursor" in description
