"""A read answer is freed when the SDK and the caller drop it, not at the next cyclic garbage
collection (facesynth_client.client.unbind, issue 23): httpx binds each response's stream to
the response itself, a cycle that kept every per-frame body (9 MB with maps) alive for
several calls, so the next ones were read into fresh memory, faulting in every page."""

from __future__ import annotations

import asyncio
import gc
import weakref

import httpx
import numpy as np
import pytest

from facesynth_client import AsyncClient, Client, npz_bytes

VERTICES = np.arange(12, dtype=np.float32).reshape(1, 4, 3)


def answer(request: httpx.Request) -> httpx.Response:
    return httpx.Response(200, headers={"content-type": "application/x-npz"},
                          content=npz_bytes(vertices=VERTICES, clamped=np.zeros(1, np.float32)))


@pytest.mark.parametrize("copy", [True, False])
def test_a_synthesis_answer_is_freed_without_the_cyclic_collector(copy):
    responses: list[weakref.ref] = []
    http = httpx.Client(transport=httpx.MockTransport(answer),
                        event_hooks={"response": [lambda r: responses.append(weakref.ref(r))]})
    with Client("http://fs.test", http_client=http) as fs:
        gc.collect()
        gc.disable()
        try:
            out = fs.synthesis.synthesize("mdl_1", np.zeros((1, 3, 3)), outputs="mesh",
                                          reuse_topology=False, copy=copy)
            np.testing.assert_array_equal(out["vertices"], VERTICES)
            assert len(responses) == 1 and responses[0]() is None        # freed on return
        finally:
            gc.enable()
    http.close()


def test_an_async_answer_is_freed_without_the_cyclic_collector():
    responses: list[weakref.ref] = []

    async def main():
        http = httpx.AsyncClient(transport=httpx.MockTransport(answer), event_hooks={
            "response": [lambda r: _async_append(responses, r)]})
        async with AsyncClient("http://fs.test", http_client=http) as fs:
            out = await fs.synthesis.synthesize("mdl_1", np.zeros((1, 3, 3)), outputs="mesh",
                                                reuse_topology=False, copy=False)
        await http.aclose()
        return out

    gc.collect()
    gc.disable()
    try:
        out = asyncio.run(main())
        np.testing.assert_array_equal(out["vertices"], VERTICES)
        assert len(responses) == 1 and responses[0]() is None
    finally:
        gc.enable()


async def _async_append(responses: list, response: httpx.Response) -> None:
    responses.append(weakref.ref(response))
