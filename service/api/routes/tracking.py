"""Performance-flow tracking (fyffe et al., Digital Ira course 2014): video of a performance
plus static scans → a tracked mesh sequence with per-frame scan weights and maps (a job)."""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Query, Request, Response, status
from fastapi.concurrency import run_in_threadpool

from service.api import bodies
from service.api.deps import ServicesDep, SubmitDep
from service.api.routes import body, inline_schema, problems, set_job_location
from service.app import schemas, uploads
from service.app.tracking import MAP_RESOLUTION, MAX_MAP_RESOLUTION, Calibration, submit_tracking
from service.jobs.formats import RESULT_FORMATS
from service.jobs.track_stages import STAGES

router = APIRouter(tags=["tracking"])

_PARTS = {
    "cameras": {**inline_schema(Calibration), "description": (
        "JSON (a file part or a field): the calibrated views, OpenCV pinhole convention "
        "(`x_cam = R X + t`, pixel `(K x)[:2] / x_z`, pixel centres at integer + 0.5), lengths "
        "in the actor's unit; 1 to 16 views, every view the same image size, the same for "
        "the scans and the performance.")},
    "scans": {"type": "array", "items": {"type": "string", "format": "binary"}, "description": (
        "One `.obj` or `.ply` raw scan mesh per static scan (not in correspondence with the "
        "neutral), in order; the first is the neutral expression. A scan's name is its file "
        "stem.")},
    "scan_images": {"type": "string", "format": "binary", "description": (
        "A zip with one image per scan and view: `<scan>/<view>.png` or `.exr` (with one view "
        "also `<scan>.png`). 8/16-bit PNG (grey or colour) or EXR (`Y` or `R`,`G`,`B`, linear); "
        "used as 8-bit luminance.")},
    "frames": {"type": "array", "items": {"type": "string", "format": "binary"}, "description": (
        "The performance per view: one zip of image sequences `<view>/<frame>.png|.exr` "
        "(natural name order; with one view also flat), or one video file per view in the "
        "calibration's order (`.mp4`, `.mov`, `.avi`, `.mkv`, ...; decoded with OpenCV).")},
    "params": {"type": "string", "description": (
        "JSON object of tracking parameters (`TrackingParams`: `hat_slope` 0.04, "
        "`stop_fraction` 0.2, `candidate_stride` 5, `graph_scale` 0.5, `keyframe_iterations`, "
        "`span_iterations`, ...; see the `TrackingParams` schema).")},
    "scan_maps": {"type": "string", "format": "binary", "description": (
        "Optional `.npz`: maps in the neutral's UV layout, one per scan, each array (S,h,w) or "
        "(S,h,w,C) (e.g. `albedo`, `displacement`); each is blended per frame into `maps.npz`.")},
}


@router.post(
    "/v1/actors/{actor_id}/tracking-jobs", status_code=status.HTTP_202_ACCEPTED,
    response_model=schemas.JobAccepted, summary="Track a performance from video (a job)",
    responses=problems(400, 404, 409, 413, 415, 422, 503),
    openapi_extra=body((), multipart=_PARTS, description=(
        "`multipart/form-data` with the parts `cameras`, `scans`, `scan_images`, `frames` "
        "and optional `params`, `scan_maps`.")),
    description=(
        "Performance-flow tracking (Fyffe et al., \"Driving High-Resolution Facial Scans with "
        "Video Performance Capture\", Digital Ira course 2014, §3–7) on the actor's neutral "
        "(the artist mesh, already uploaded): a performance flow graph of optical flows "
        "between the frames and from static scans to selected frames, then the coupled "
        "solve of the keyframes and static poses, then each in-between span independently. "
        "Answers 202 with `{job_id}` and `Location: /v1/jobs/{job_id}`.\n\n"
        "The job (kind `track`) reports `stage` ∈ " + ", ".join(f"`{s}`" for s in STAGES) +
        " with `progress`, and can be cancelled (its span jobs are cancelled with it). It "
        "fans out one child job (kind `track_span`) per in-between span through the queue, "
        "so more workers finish a long performance sooner; a worker that dies costs one span. "
        "Its result holds `artifacts` (file name → id): `tracked.npz` (`vertices` (T,n,3) "
        "float32 world, `faces`, `rotations` (T,3,3), `translations` (T,3), `keyframes`, "
        "`static_edges` (E,2) (scan, frame), `scan_names`), `weights.npz` (`weights` (T,n,S) "
        "per-frame per-vertex weights over the scans, rows summing to 1), `maps.npz` "
        "(`reflectance` (T,h,w) — the scans' images re-projected into the UV layout, blended "
        "per frame — and each uploaded `scan_maps` array, blended), `scans.npz` (`vertices` "
        "(S,n,3) the static scans registered to the neutral's topology, NaN for scans the "
        "graph did not use, `registered` (S,), `reflectance` (S,h,w)); with "
        "`format=obj-exr-zip` also `tracked.zip` (one OBJ per frame), with `format=usd` "
        "`tracked.usd`; and `metrics` (frames, keyframes, spans, edges, seconds per stage), "
        "`span_job_ids`.\n\n"
        "Refusals name what is wrong: no neutral (409); a missing part, a bad calibration "
        "(not 3×3, not a rotation, fx ≤ 0, views of different sizes), an unreadable mesh, "
        "image, zip or video, an image whose size differs from its view's calibration, "
        "views with different frame counts, fewer than 2 frames, a missing scan image, "
        "video files not one per view, bad params (422); a body over the limit (413)."))
async def submit_tracking_job(
        actor_id: str, request: Request, services: ServicesDep, submit: SubmitDep,
        response: Response,
        result_format: Annotated[schemas.ResultFormat, Query(alias="format", description=(
            "`npz` (default: the NPZ artifacts only); `obj-exr-zip` adds `tracked.zip` (an OBJ "
            "per frame with the neutral's UVs); `usd` adds `tracked.usd` (a point cache)."))] = "npz",
        map_resolution: Annotated[int, Query(ge=8, le=MAX_MAP_RESOLUTION, description=(
            "side of the blended maps, texels"))] = MAP_RESOLUTION,
) -> schemas.JobAccepted:
    bodies.require_media_type(request, (uploads.MULTIPART,))
    form = await bodies.read_tracking_form(request)
    job_id = await run_in_threadpool(submit_tracking, services, submit, actor_id, form,
                                     result_format=result_format, map_resolution=map_resolution)
    set_job_location(response, job_id)
    return schemas.JobAccepted(job_id=job_id)
