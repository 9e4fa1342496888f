"""An actor's facial scans (UV-space maps) and scan correspondence (a job)."""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Body, Depends, Query, Request, Response, status
from fastapi.concurrency import run_in_threadpool

from service.api import bodies
from service.api.query import PageDep
from service.api.deps import ServicesDep, SubmitDep
from service.api.routes import body, problems, set_job_location
from service.app import scans, schemas, uploads

router = APIRouter(prefix="/v1/actors/{actor_id}", tags=["scans"])


@router.post(
    "/scans", status_code=status.HTTP_201_CREATED, response_model=scans.Scan,
    summary="Upload a scan (UV-space maps)", responses=problems(400, 404, 413, 415, 422),
    openapi_extra=body(uploads.NPZ_TYPES, description=(
        "`.npz` of UV-space maps, all H×W: `albedo` (H,W,3) float (linear diffuse, the "
        "texture the correspondence is computed on) and `position` (H,W,3) float (the point "
        "cloud in the actor's unit) are required; `specular` (H,W,3), `normal` (H,W,3) float "
        "and `mask` (H,W) bool (the covered texels; default: albedo non-zero) are optional. "
        "Values must be finite on the covered texels (NaN or infinite values outside `mask` "
        "are stored as 0); 8 ≤ H, W ≤ 8192.")))
async def add_scan(actor_id: str, request: Request, services: ServicesDep,
                   name: Annotated[str | None, Query(max_length=200)] = None) -> scans.Scan:
    """Store a scan of the actor; answers 201 with `{scan_id, name, width, height, maps}`.
    A missing `albedo`/`position`, maps of different sizes, a wrong dtype or a non-finite
    value on a covered texel are a 422 naming the map."""
    _, data = await bodies.read_body(request, uploads.NPZ_TYPES)
    return await run_in_threadpool(scans.add_scan, services, actor_id, data, name)


@router.get("/scans", response_model=scans.ScanList, summary="List an actor's scans",
            responses=problems(404))
async def list_scans(actor_id: str, services: ServicesDep, page: PageDep) -> scans.ScanList:
    """The actor's scans, oldest first, a page at a time (`limit`, `cursor`)."""
    return await run_in_threadpool(scans.list_scans, services, actor_id, page)


@router.get("/scans/{scan_id}", response_model=scans.Scan, summary="Get a scan",
            responses=problems(404))
async def get_scan(actor_id: str, scan_id: str, services: ServicesDep) -> scans.Scan:
    """One scan of the actor."""
    return await run_in_threadpool(scans.get_scan, services, actor_id, scan_id)


@router.delete("/scans/{scan_id}", status_code=status.HTTP_204_NO_CONTENT,
               summary="Delete a scan", responses=problems(404))
async def delete_scan(actor_id: str, scan_id: str, services: ServicesDep) -> Response:
    """Delete a scan and its maps (results of correspondence jobs are kept)."""
    await run_in_threadpool(scans.delete_scan, services, actor_id, scan_id)
    return Response(status_code=status.HTTP_204_NO_CONTENT)


@router.post(
    "/correspondence-jobs", status_code=status.HTTP_202_ACCEPTED,
    response_model=schemas.JobAccepted, summary="Correspond two scans (a job)",
    dependencies=[Depends(bodies.require_json)],
    responses=problems(400, 404, 409, 415, 422, 503),
    description=(
        "Warp the source scan into the target scan's UV space (Vuvuzela: a Delaunay "
        "piecewise-affine pre-warp from the landmarks, a dense optical flow on over-sharpened "
        "diffuse textures, the composed warp applied to every map). Answers 202 with "
        "`{job_id}` and `Location: /v1/jobs/{job_id}`. The job's artifacts: one EXR per "
        "warped map (`albedo.exr`, `position.exr`, ...; channels R, G, B), `warp.npz` "
        "(`coords` (H,W,2) source texel of every target texel, `confidence` (H,W), `mask` "
        "(H,W), `prewarp`, `flow`), and with `artist_uv` `blendshape.npz` (`vertices` (n,3), "
        "`valid` (n,)). Its result holds `artifacts` (file name → id) and `metrics` "
        "(`mean_confidence`, `coverage`, `seconds`).\n\n"
        "Refusals: an unknown scan or one of another actor (404); fewer than 3 landmarks, "
        "coordinates outside [0, 1], a pinned index past the landmarks, or scans holding "
        "different maps (422); `artist_uv` without a neutral (409)."))
async def submit_correspondence(actor_id: str,
                                request_body: Annotated[scans.CorrespondenceJob, Body()],
                                services: ServicesDep, submit: SubmitDep,
                                response: Response) -> schemas.JobAccepted:
    accepted = await run_in_threadpool(scans.submit_correspondence, services, submit, actor_id,
                                       request_body)
    set_job_location(response, accepted.job_id)
    return accepted
