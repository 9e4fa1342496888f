"""A synthesis answer sent as the NPZ's pieces (service.api.routes.synthesis.PiecesResponse)
is on the wire what the one-buffer Response of the joined body was: status, headers and
bytes, with each HTTP implementation, on a real uvicorn server (issue 23)."""

from __future__ import annotations

import http.client
import io

import numpy as np
import pytest
from starlette.responses import Response

from service.api.connections import GuardedHttpToolsProtocol, protocol_class
from service.api.routes.synthesis import PiecesResponse
from service.io.npz import npz_parts
from tests.servers import uvicorn_thread

IMPLEMENTATIONS = ["h11"] + (["httptools"] if GuardedHttpToolsProtocol is not None else [])


def _parts():
    rng = np.random.default_rng(5)
    return npz_parts({"vertices": rng.standard_normal((1, 50_000, 3)).astype(np.float32),
                      "clamped": np.zeros(1, np.float32),
                      "displacement": rng.standard_normal((1, 512, 512)).astype(np.float32),
                      "normal_map": rng.standard_normal((1, 512, 512, 3)).astype(np.float32)},
                     {"normal_map": np.float16})


async def app(scope, receive, send):
    if scope["type"] != "http":
        return
    while (await receive()).get("more_body"):
        pass
    parts = _parts()
    headers = {"Content-Disposition": 'attachment; filename="synthesis.npz"', "X-Frames": "1"}
    response = (PiecesResponse(parts, media_type="application/x-npz", headers=headers)
                if scope["path"] == "/pieces" else
                Response(parts.join(), media_type="application/x-npz", headers=headers))
    await response(scope, receive, send)


@pytest.fixture(scope="module", params=IMPLEMENTATIONS)
def port(request):
    with uvicorn_thread(app, http=protocol_class(5.0, 200.0, 1.0, 4, http=request.param),
                        access_log=False) as port:
        yield port


def test_pieces_are_the_joined_body_on_the_wire(port):
    connection = http.client.HTTPConnection("127.0.0.1", port, timeout=30)
    answers = []
    for path in ("/pieces", "/joined", "/pieces"):          # kept alive across both
        connection.request("POST", path, body=b"x")
        response = connection.getresponse()
        answers.append((response.status, [(k, v) for k, v in response.getheaders() if k != "date"],
                        response.read()))
    connection.close()
    assert answers[0] == answers[1] == answers[2]
    status, headers, body = answers[0]
    assert status == 200 and dict(headers)["content-length"] == str(len(body)) == str(len(_parts()))
    assert body == bytes(_parts().join())
    with np.load(io.BytesIO(body)) as archive:      # CRCs checked by zipfile
        assert archive["normal_map"].dtype == np.float16
