"""Artifacts: downloadable job results, with ``ETag``, conditional and range requests."""

from __future__ import annotations

from fastapi import APIRouter, Request, Response, status
from fastapi.concurrency import run_in_threadpool
from fastapi.responses import FileResponse

from service.app import operations
from service.api.deps import ServicesDep
from service.api.routes import binary_response, etag_matches, problems

router = APIRouter(prefix="/v1/artifacts", tags=["artifacts"])


@router.get(
    "/{artifact_id}", summary="Download an artifact", response_class=FileResponse,
    responses={**binary_response("application/octet-stream", description=(
        "The file, with `Content-Length`, `ETag` (its sha256) and `Accept-Ranges: bytes`.")),
        206: {"description": "The requested byte range (`Range: bytes=a-b`)."},
        304: {"description": "Not modified (`If-None-Match` matched the ETag)."},
        416: {"description": "Range not satisfiable."}, **problems(404)})
async def get_artifact(artifact_id: str, request: Request, services: ServicesDep) -> Response:
    """A job's result file. Its ETag is the sha256 of its content; `If-None-Match` gives
    304, `Range` a 206 partial answer (416 outside the file; `If-Range` honoured)."""
    artifact, path = await run_in_threadpool(operations.artifact_file, services, artifact_id)
    etag = f'"{artifact.sha256}"'
    if etag_matches(request.headers.get("if-none-match"), etag):
        return Response(status_code=status.HTTP_304_NOT_MODIFIED, headers={"ETag": etag})
    return FileResponse(path, media_type=artifact.media_type, filename=artifact.filename,
                        headers={"ETag": etag})

