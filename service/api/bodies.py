"""Reading request bodies: media types, the whole body, multipart forms (clips, rigs, files),
and the body-size limit enforced while a body streams in (the parsing of what was read is
:mod:`service.app.uploads`)."""

from __future__ import annotations

import contextlib
import hashlib
import os
from pathlib import Path
from typing import Any, AsyncIterator, Sequence

from fastapi import Request
from fastapi.concurrency import run_in_threadpool
from starlette.datastructures import UploadFile
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from service.api.errors import BodyTooLarge, problem
from service.app.limits import MULTIPART_MAX_FIELD_BYTES, MULTIPART_MAX_FILES
from service.app.uploads import (JSON_TYPE, MESH_TYPES, NPZ_TYPES, OBJ_TYPES, ClipForm,
                                 TrackingForm)
from service.errors import InvalidInput, MalformedInput, UnsupportedFormat


def media_type(request: Request) -> str:
    """The request's media type, lower case, without parameters ("" if none)."""
    return request.headers.get("content-type", "").split(";")[0].strip().lower()


def require_media_type(request: Request, allowed: Sequence[str]) -> str:
    """The request's media type if it is one of ``allowed``, else 415 naming them."""
    kind = media_type(request)
    if kind not in allowed:
        given = f"Content-Type '{kind}'" if kind else "a request without Content-Type"
        raise UnsupportedFormat(f"{given} is not accepted here; send one of: "
                                   f"{', '.join(allowed)}")
    return kind


@contextlib.asynccontextmanager
async def body_source(request: Request, allowed: Sequence[str]
                      ) -> AsyncIterator[tuple[str, bytes | Path]]:
    """The media type (one of ``allowed``) and the non-empty body: its bytes, or — for a
    body larger than ``spool_body_bytes`` — the path of its spool file, which lives until
    the block ends.

    The size limit is enforced while the body streams in (:class:`BodyLimitMiddleware`). A
    large body is never gathered in memory: it is written, chunk by chunk as it arrives, to
    a hidden scratch directory of the blob store (its filesystem has the room, the sweep
    removes what a killed process leaves, and the canonical blob written beside it is moved
    into place) while its sha256 is computed (``request.state.body_sha256``); the directory
    is removed when the block ends, however it ends (issue 16, defect 11). Routes whose
    parser reads a file (:class:`~service.app.uploads.NpzUpload`) pass the path on, inside
    the block.
    """
    kind = require_media_type(request, allowed)
    services = getattr(request.app.state, "services", None)
    declared = request.headers.get("content-length", "")
    threshold = services.settings.spool_body_bytes if services is not None else None
    if threshold is None or (declared.isdigit() and int(declared) <= threshold):
        data = await request.body()
        if not data:
            raise MalformedInput(f"the request body is empty; send a {kind} body")
        yield kind, data
        return
    with services.blobs.scratch_dir("upload") as directory:
        path = directory / "body"
        request.state.body_sha256 = await _spool(request, path)
        if not os.path.getsize(path):
            raise MalformedInput(f"the request body is empty; send a {kind} body")
        yield kind, path


async def read_body(request: Request, allowed: Sequence[str]) -> tuple[str, bytes]:
    """The media type (one of ``allowed``) and the whole, non-empty body in memory (a large
    body is spooled as :func:`body_source` does, then read back once: for the routes whose
    parser needs bytes; the uploads that can be large take :func:`body_source`)."""
    async with body_source(request, allowed) as (kind, data):
        if isinstance(data, Path):
            data = await run_in_threadpool(data.read_bytes)
        return kind, data


async def _spool(request: Request, path: Path) -> str:
    """Stream the body into the new file ``path``; its sha256 hex digest."""
    digest = hashlib.sha256()
    with open(path, "wb") as spool:
        async for chunk in request.stream():
            if chunk:
                digest.update(chunk)
                await run_in_threadpool(spool.write, chunk)
    return digest.hexdigest()


class LargeUploadLimiter:
    """At most ``limit`` requests with a large body (a declared ``Content-Length`` over
    ``threshold`` bytes, or a chunked body) are served at once; one more waits up to
    ``wait_seconds`` for its turn, then is answered 503 with ``Retry-After`` — so a burst of
    big uploads cannot take the server's memory (issue 16: four 250 MiB bodies at once used
    1.4 GB)."""

    def __init__(self, app: ASGIApp, limit: int, threshold: int, wait_seconds: float):
        import asyncio

        self.app, self.threshold, self.wait_seconds = app, threshold, wait_seconds
        self.limit = limit
        self._slots = asyncio.Semaphore(limit)
        self.waiting = 0

    def _large(self, scope: Scope) -> bool:
        headers = dict(scope.get("headers", ()))
        declared = headers.get(b"content-length")
        if declared is not None:
            return declared.isdigit() and int(declared) > self.threshold
        return b"chunked" in headers.get(b"transfer-encoding", b"")

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        import asyncio

        if scope["type"] != "http" or not self._large(scope):
            await self.app(scope, receive, send)
            return
        self.waiting += 1
        try:
            await asyncio.wait_for(self._slots.acquire(), timeout=self.wait_seconds)
        except asyncio.TimeoutError:
            from starlette.requests import Request as StarletteRequest

            response = problem(StarletteRequest(scope), 503,
                               f"{self.limit} large uploads are being received already; retry "
                               "shortly", slug="overloaded", headers={"Retry-After": "2"})
            await response(scope, receive, send)
            return
        finally:
            self.waiting -= 1
        try:
            await self.app(scope, receive, send)
        finally:
            self._slots.release()


async def read_form(request: Request) -> Any:
    """The multipart form of the request (files spooled to disk by Starlette; the body limit
    applies as it streams in; a broken stream is a 400)."""
    return await request.form(max_files=MULTIPART_MAX_FILES, max_fields=64,
                              max_part_size=MULTIPART_MAX_FIELD_BYTES)


async def require_json(request: Request) -> None:
    """Dependency of routes whose body is a JSON model: any other media type is a 415
    (FastAPI alone would answer a 422 'field required')."""
    if request.headers.get("content-length", "0") != "0" or "transfer-encoding" in request.headers:
        require_media_type(request, (JSON_TYPE,))


class BodyLimitMiddleware:
    """Refuses request bodies over ``limit`` bytes with a 413 naming the limit: at once when
    ``Content-Length`` declares more, else as soon as the streamed body passes it (before
    it has all been read)."""

    def __init__(self, app: ASGIApp, limit: int):
        self.app = app
        self.limit = limit

    def _error(self, size: str) -> BodyTooLarge:
        return BodyTooLarge(f"the request body is {size}, more than the limit of "
                               f"{self.limit} bytes (max_body_bytes); send large work as a job "
                               "or split it")

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        declared = dict(scope.get("headers", ())).get(b"content-length")
        if declared is not None and declared.isdigit() and int(declared) > self.limit:
            from starlette.requests import Request as StarletteRequest

            error = self._error(f"{int(declared)} bytes")
            response = problem(StarletteRequest(scope), 413, error.detail)
            await response(scope, receive, send)
            return
        received = 0

        async def counting_receive() -> Message:
            nonlocal received
            message = await receive()
            if message["type"] == "http.request":
                received += len(message.get("body", b""))
                if received > self.limit:
                    raise self._error(f"over {received} bytes")
            return message

        await self.app(scope, counting_receive, send)


# ---------------------------------------------------------------------------- multipart
async def read_clip_form(request: Request) -> ClipForm:
    """Read a multipart clip: parts ``frames`` (one ``.obj`` file per frame, in order),
    ``markers`` (a ``.c3d``, ``.trc``, ``.csv`` or ``.json`` file), optional ``fps``."""
    form = await read_form(request)
    frames = [part for part in form.getlist("frames") if isinstance(part, UploadFile)]
    markers = form.get("markers")
    if not frames:
        raise InvalidInput("a multipart clip needs one or more 'frames' parts (.obj files, one "
                           "per frame, in order)")
    if not isinstance(markers, UploadFile):
        raise InvalidInput("a multipart clip needs a 'markers' file part (.c3d, .trc, .csv "
                           "or .json)")
    fps = form.get("fps")
    try:
        fps_value = None if fps in (None, "") else float(fps)
    except (TypeError, ValueError):
        raise InvalidInput(f"'fps' must be a number, got {str(fps)[:40]!r}") from None
    return ClipForm([(f.filename or f"frame {k}", await f.read()) for k, f in enumerate(frames)],
                    (markers.filename or "", await markers.read()), fps_value)

async def read_rig_form(request: Request) -> tuple[str, bytes, str | None]:
    """A multipart input rig: a ``mesh`` file part (``.npz`` or ``.obj``, by its filename or
    its part's Content-Type) and an optional ``landmarks`` JSON field.

    Returns
    -------
    (media type, mesh bytes, landmarks text or None)
    """
    form = await read_form(request)
    mesh = form.get("mesh")
    if not isinstance(mesh, UploadFile):
        raise InvalidInput("a multipart input rig needs a 'mesh' file part (.npz or .obj)")
    suffix = (mesh.filename or "").rsplit(".", 1)[-1].lower()
    part_type = (mesh.content_type or "").split(";")[0].strip().lower()
    kind = {"npz": NPZ_TYPES[0], "obj": OBJ_TYPES[0]}.get(suffix, part_type)
    if kind not in MESH_TYPES:
        raise UnsupportedFormat(f"the 'mesh' part '{mesh.filename}' is neither .npz nor "
                                   f".obj (Content-Type '{part_type}')")
    landmarks = form.get("landmarks")
    if isinstance(landmarks, UploadFile):
        landmarks = (await landmarks.read()).decode("utf-8", "replace")
    return kind, await mesh.read(), landmarks

async def read_file_part(request: Request, name: str) -> tuple[str, bytes]:
    """The filename and content of the file part ``name`` of a multipart body."""
    form = await read_form(request)
    part = form.get(name)
    if not isinstance(part, UploadFile):
        raise InvalidInput(f"the multipart body needs a file part '{name}'")
    return part.filename or "", await part.read()


#: the parts of a tracking upload (``POST /v1/actors/{id}/tracking-jobs``)
TRACKING_PARTS = ("cameras", "scans", "scan_images", "frames", "params", "scan_maps")


async def read_tracking_form(request: Request) -> TrackingForm:
    """A multipart tracking upload (:mod:`service.app.tracking`): its file parts stay in
    Starlette's spool files (on disk past 1 MiB), read by the operation in the thread pool;
    ``cameras`` and ``params`` may be file parts or plain fields. An unknown part is a 422
    naming the known ones."""
    form = await read_form(request)
    unknown = sorted(set(form.keys()) - set(TRACKING_PARTS))
    if unknown:
        raise InvalidInput(f"unknown part(s) {unknown} in the tracking upload; its parts are "
                           f"{', '.join(TRACKING_PARTS)}")

    async def text(name: str) -> str | bytes | None:
        value = form.get(name)
        if isinstance(value, UploadFile):
            return await value.read()
        return value

    def files(name: str) -> list[tuple[str, Any]]:
        parts = form.getlist(name)
        loose = [p for p in parts if not isinstance(p, UploadFile)]
        if loose:
            raise InvalidInput(f"the '{name}' part must be a file (got a plain field)")
        return [(p.filename or f"{name}-{k}", p.file) for k, p in enumerate(parts)]

    def one(name: str) -> tuple[str, Any] | None:
        parts = files(name)
        if len(parts) > 1:
            raise InvalidInput(f"send one '{name}' part, got {len(parts)}")
        return parts[0] if parts else None

    cameras, params = await text("cameras"), await text("params")
    if isinstance(cameras, str):
        cameras = cameras.encode()
    if isinstance(params, bytes):
        params = params.decode("utf-8", "replace")
    return TrackingForm(cameras, files("scans"), one("scan_images"), files("frames"), params,
                        one("scan_maps"))
