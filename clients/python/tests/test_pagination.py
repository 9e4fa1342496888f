"""Listings are read whole from a server that pages them (``next_cursor``, sent back as
``cursor``) and from one that does not (one page), by both clients."""

from __future__ import annotations

import asyncio

import httpx
import pytest

from facesynth_client import AsyncClient, Client, TransportError


def paged_jobs(pages: list[list[str]], requests: list[httpx.URL]):
    """A ``GET /v1/jobs`` handler answering ``pages`` in turn, chained by cursors."""

    def handler(request: httpx.Request) -> httpx.Response:
        requests.append(request.url)
        cursor = request.url.params.get("cursor")
        index = 0 if cursor is None else int(cursor.removeprefix("c"))
        body = {"items": [{"id": j, "kind": "train", "status": "succeeded"} for j in pages[index]]}
        if index + 1 < len(pages):
            body["next_cursor"] = f"c{index + 1}"
        return httpx.Response(200, json=body)

    return handler


def test_a_paged_listing_is_followed_to_its_last_page_keeping_the_filters():
    requests: list[httpx.URL] = []
    pages = [["job_a", "job_b"], ["job_c"], ["job_d", "job_e"]]
    with Client("http://test", transport=httpx.MockTransport(paged_jobs(pages, requests))) as fs:
        jobs = fs.jobs.list(status="succeeded")
    assert [j.id for j in jobs] == ["job_a", "job_b", "job_c", "job_d", "job_e"]
    assert [u.params.get("cursor") for u in requests] == [None, "c1", "c2"]
    assert all(u.params["status"] == "succeeded" for u in requests)


def test_an_unpaged_listing_is_one_request_and_the_async_client_pages_too():
    requests: list[httpx.URL] = []
    with Client("http://test", transport=httpx.MockTransport(
            paged_jobs([["job_a"]], requests))) as fs:
        assert [j.id for j in fs.jobs.list()] == ["job_a"]
    assert len(requests) == 1

    async def run() -> list[str]:
        async with AsyncClient("http://test", transport=httpx.MockTransport(
                paged_jobs([["job_a"], ["job_b"]], []))) as fs:
            return [j.id for j in await fs.jobs.list()]

    assert asyncio.run(run()) == ["job_a", "job_b"]


def test_a_cursor_the_server_repeats_is_an_error_not_a_loop():
    def handler(request: httpx.Request) -> httpx.Response:
        return httpx.Response(200, json={"items": [], "next_cursor": "same"})

    with Client("http://test", transport=httpx.MockTransport(handler)) as fs:
        with pytest.raises(TransportError, match="repeated the page cursor 'same'"):
            fs.actors.list()
