"""Synthesis: synchronous for a frame or a small batch, and synthesis jobs for whole
performances."""

from __future__ import annotations

from typing import Annotated, Literal

from fastapi import APIRouter, Header, Query, Request, Response, status
from pydantic import Field
from fastapi.concurrency import run_in_threadpool
from starlette.types import Receive, Scope, Send

from service.api import bodies
from service.app import operations, schemas, uploads
from service.api.deps import ServicesDep, SubmitDep
from service.api.routes import (binary_response, body, etag_matches, inline_schema, problems,
                                set_job_location)
from service.app.synthesis import EXR, JOB_INPUT_TYPES, NPZ, OBJ, RESPONSE_TYPES, parse_outputs
from service.geometry.marker_filter import MAX_SIGMA_FRAMES
from service.io.npz import NpzParts
from service.methods.outputs import DEFAULT_OUTPUTS

router = APIRouter(prefix="/v1/models/{model_id}", tags=["synthesis"])

OutputsQuery = Annotated[list[str] | None, Query(
    description="Subset of `mesh`, `mesh_detailed`, `displacement`, `albedo`, `normal_map` "
                "(comma-separated or repeated; default `mesh,displacement`).",
    examples=["mesh,displacement"])]
RigQuery = Annotated[str | None, Query(
    pattern=schemas.RIG_NAME_PATTERN,
    description="Name of a registered input rig of the model's actor "
                "(`PUT /v1/actors/{actor_id}/input-rigs/{rig}`): the frames' `vertices` are "
                "(F,v,3) on that rig's topology and are carried to the actor's by its "
                "registration. 404 for an unknown rig, 409 while it is registering or if its "
                "registration failed.",
    examples=["game-lod2"])]
HalfQuery = Annotated[bool, Query(
    description="16-bit (half) floats for the maps: an EXR with half channels, or in an "
                "`.npz` the maps `displacement`, `albedo`, `normal_map` as float16 (half the "
                "bytes; each value within 2⁻¹¹ relative, 2⁻²⁵ absolute, of the float32 one). "
                "Meshes stay float32.")]
TopologyQuery = Annotated[bool, Query(
    description="`false`: leave `faces` out of an `.npz` response (a client that repeats "
                "calls fetches them once from `GET /v1/models/{model_id}/topology`, "
                "revalidated with its `ETag`).")]
_RESPONSES = {
    **binary_response(*RESPONSE_TYPES, description=(
        "`application/x-npz` (default): `vertices` (F,V,3) in the input's world pose, "
        "`vertices_detailed` (F,V,3) for `mesh_detailed`, `faces` (T,3), the asked maps "
        "(`displacement` (F,H,W), `albedo` (F,H,W,3), `normal_map` (F,H,W,3)) and `clamped` "
        "(F,) the fraction of texels held at the extrapolation limit; models that report a "
        "confidence add `confidence` (F,) in [0, 1] (1: the neutral, inside the training "
        "data, with clean markers; lower beyond the training data, for larger deformations "
        "and for noisier markers) and, for `pdm`, "
        "`confidence_vertices` (F,V). `Accept: model/obj`: one "
        "frame as OBJ with UVs; `Accept: image/x-exr` with one map output: that map as EXR.")),
    **problems(400, 404, 406, 409, 413, 415, 422, 503)}
_RESPONSES[200]["headers"] = {
    operations.CONFIDENCE_HEADER: {
        "description": "Per-frame confidence in [0, 1], comma-separated in frame order (4 "
                       "decimals), for models that report one (`pdm`, `psd`, `wpsd`): how far "
                       "the frame's deformation lies outside what the model was trained on (1: "
                       "inside), times how much of the marker signal the frame's markers still "
                       "determine (their own noise estimate and the share of the signal hidden "
                       "by occlusion), times exp(−size / (3.5 × the training's RMS size)) of "
                       "the frame's marker deformation. The detail is faded toward the thin "
                       "shell (and, for `pdm`, the static neutral map) by the first factor "
                       "alone (`pdm` with "
                       "`clamp`, `psd`/`wpsd` with `confidence_fade`).",
        "schema": {"type": "string", "example": "1.0000,0.9731"}}}


async def _synthesize(model_id: str, request: Request, services: ServicesDep, outputs: list[str] | None,
                      clamp: bool, half: bool, accept: str | None, route_input: str,
                      rig: str | None = None, topology: bool = True) -> Response:
    kind, data = await bodies.read_body(
        request, uploads.NPZ_TYPES + ((uploads.JSON_TYPE,) if route_input == "markers" else ()))
    answer = await request.app.state.synthesis_threads.run(
        lambda: operations.synthesize(services, request.app.state.synthesizer, model_id, kind,
                                      data, accept=accept, outputs=parse_outputs(outputs),
                                      clamp=clamp, half=half, route_input=route_input, rig=rig,
                                      topology=topology))
    return _answer(answer, "synthesis")


class PiecesResponse(Response):
    """A response whose body is an NPZ's :class:`~service.io.npz.NpzParts`, sent as its
    pieces, one ``http.response.body`` message each: the server writes the arrays' own
    memory instead of a copy of them joined into one buffer (a level-1 maps frame: 8.9 MB
    not copied). The status, headers and bytes are those of ``Response(parts.join())``."""

    def render(self, content: NpzParts) -> NpzParts:     # type: ignore[override]
        return content              # its len() is the Content-Length

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        await send({"type": "http.response.start", "status": self.status_code,
                    "headers": self.raw_headers})
        pieces = self.body.pieces
        for k, piece in enumerate(pieces):
            await send({"type": "http.response.body", "body": piece,
                        "more_body": k + 1 < len(pieces)})


def _answer(answer: operations.Synthesized, name: str) -> Response:
    suffix = {NPZ: "npz", OBJ: "obj", EXR: "exr"}[answer.media_type]
    headers = {"Content-Disposition": f'attachment; filename="{name}.{suffix}"',
               "X-Frames": str(answer.frames)}
    if answer.confidence is not None:
        headers[operations.CONFIDENCE_HEADER] = answer.confidence
    kind = PiecesResponse if isinstance(answer.body, NpzParts) else Response
    return kind(answer.body, media_type=answer.media_type, headers=headers)


@router.post(
    "/synthesize", summary="Synthesize meshes and maps from markers", response_class=Response,
    responses=_RESPONSES,
    openapi_extra=body(uploads.NPZ_TYPES, json_schema=inline_schema(schemas.SynthesizeBody),
                       description="`.npz` with `markers` (F,M,3) (NaN: occluded), or JSON."))
async def synthesize(model_id: str, request: Request, services: ServicesDep,
                     outputs: OutputsQuery = None, clamp: bool = True,
                     half: HalfQuery = False, topology: TopologyQuery = True,
                     accept: Annotated[str | None, Header()] = None) -> Response:
    """For marker-driven kinds (e.g. `pdm`): markers in, detailed meshes and maps out, for
    at most `max_frames_per_request` frames (413 above: use a synthesis job). 409 while the
    model is not ready; 422 for a wrong marker count ("model expects 150 markers, got 149")."""
    return await _synthesize(model_id, request, services, outputs, clamp, half, accept, "markers",
                             topology=topology)


@router.post(
    "/enhance", summary="Enhance low-resolution meshes", response_class=Response,
    responses=_RESPONSES,
    openapi_extra=body(uploads.NPZ_TYPES, description="`.npz` with `vertices` (F,V,3) of the "
                                                      "actor's topology, or (F,v,3) of the input "
                                                      "rig named by `rig`."))
async def enhance(model_id: str, request: Request, services: ServicesDep,
                  outputs: OutputsQuery = None, clamp: bool = True,
                  half: HalfQuery = False, topology: TopologyQuery = True,
                  rig: RigQuery = None,
                  accept: Annotated[str | None, Header()] = None) -> Response:
    """For mesh-driven kinds (e.g. `shape_space`): meshes in, detailed meshes and maps out;
    the response is as for `/synthesize` (a `shape_space` model's `displacement` is the
    detail over the input surface: the enhanced mesh's offset plus the database's blended
    fine maps; `albedo` is the database's blended albedo maps where it had them; it adds its
    matching `weights` (F,R,N)). With `rig`, the vertices are on
    that registered input rig (422 naming its vertex count if they are not). A
    marker-driven model answers 422."""
    return await _synthesize(model_id, request, services, outputs, clamp, half, accept, "meshes",
                             rig, topology)


@router.get(
    "/topology", summary="Get a model's topology (cacheable)", response_class=Response,
    responses={**binary_response(NPZ, description=(
        "`application/x-npz`: `faces` (T,3) int32 — the triangles of every synthesis "
        "response — and, where the model has them, `uv` (K,2) and `uv_faces` (T,3) int32. "
        "With a strong `ETag` (a hash of the arrays) and `Cache-Control: private, "
        "no-cache`: revalidate with `If-None-Match`.")),
        304: {"description": "Not modified (`If-None-Match` matched the ETag)."},
        **problems(404, 409, 503)})
async def get_topology(model_id: str, request: Request, services: ServicesDep) -> Response:
    """The model's triangles (and UVs), which `/synthesize` and `/enhance` leave out with
    `topology=false`: a client that calls them repeatedly fetches this once, keeps it by
    its `ETag`, and revalidates with `If-None-Match` (304 while it is unchanged — for a
    model, as long as it exists). 409 while the model is not ready."""
    topology = await run_in_threadpool(operations.model_topology, services, model_id)
    headers = {"ETag": topology.etag, "Cache-Control": "private, no-cache"}
    if etag_matches(request.headers.get("if-none-match"), topology.etag):
        return Response(status_code=status.HTTP_304_NOT_MODIFIED, headers=headers)
    return Response(topology.body, media_type=NPZ, headers={
        **headers, "Content-Disposition": 'attachment; filename="topology.npz"'})


@router.post(
    "/retime", summary="Retime keyframes (shape_space)", response_class=Response,
    responses={**binary_response(NPZ, description=(
        "`application/x-npz`: `vertices` (m,V,3) float32 on the actor's topology (keyframe k "
        "exactly at output frame `keyframe_indices[k]`), `timestamps` (m,) in output frame "
        "units, `progress` (m,) in keyframe units (k + the blend fraction within segment k), "
        "`region_progress` (R,m), `keyframe_indices` (K,), per segment `segment_sequences` "
        "(K-1,R) and `segment_spans` (K-1,R,2) (the matched database motion), "
        "`region_names` (R,) and `faces` (T,3).")),
        **problems(400, 404, 409, 413, 415, 422, 503)},
    openapi_extra=body(uploads.NPZ_TYPES, json_schema=inline_schema(schemas.RetimeBody),
                       description="JSON, or `.npz` with `keyframes` (K,v,3) and the query "
                                   "parameters `length`, `extend_to_full_motion`, `rig`."))
async def retime(model_id: str, request: Request, services: ServicesDep,
                 length: Annotated[int | None, Query(
                     ge=2, description="Output frames m (`.npz` bodies; JSON bodies carry "
                                       "`length`).")] = None,
                 extend_to_full_motion: Annotated[bool | None, Query(
                     description="Extend the matched database motion (`.npz` bodies).")] = None,
                 rig: RigQuery = None) -> Response:
    """Temporal enhancement of `shape_space` models (bermano2014 §6.2): two or more keyframes
    (vertices, or frames of the actor's clips) in, `length` frames out whose timing follows
    the database's dynamics. With K keyframes, keyframe k is output frame
    round(k (length-1)/(K-1)) and each consecutive pair is retimed over its segment. Other
    kinds answer 422; K or `length` above `max_frames_per_request` answer 413."""
    kind, data = await bodies.read_body(request, uploads.NPZ_TYPES + (uploads.JSON_TYPE,))
    answer = await run_in_threadpool(
        lambda: operations.retime(services, request.app.state.synthesizer, model_id, kind, data,
                                  length=length, extend=extend_to_full_motion, rig=rig))
    return _answer(answer, "retime")


@router.post(
    "/synthesis-jobs", status_code=status.HTTP_202_ACCEPTED, response_model=schemas.JobAccepted,
    summary="Synthesize a whole performance (a job)",
    responses=problems(400, 404, 409, 413, 415, 422, 503),
    openapi_extra=body(tuple(t for t in JOB_INPUT_TYPES if t != uploads.JSON_TYPE), json_schema={
        "type": "object", "required": ["markers"],
        "properties": {"markers": {"type": "array", "description": "(F,M,3); null: occluded"},
                       "names": {"type": "array", "items": {"type": "string"}},
                       "fps": {"type": "number"}}}, multipart={
        "file": {"type": "string", "format": "binary",
                 "description": "The performance; its type from the filename (.npz, .json, "
                                ".c3d, .trc, .csv)."}},
        description="The performance: `.npz` with `markers` (F,M,3) (or `vertices` for "
                    "mesh-driven kinds), marker JSON, or a `.c3d` / `.trc` / `.csv` file."))
async def submit_synthesis_job(
        model_id: str, request: Request, services: ServicesDep, submit: SubmitDep,
        response: Response, outputs: OutputsQuery = None, clamp: bool = True,
        result_format: Annotated[schemas.ResultFormat, Query(
            alias="format", description=(
                "`npz` (default); `obj-exr-zip` for per-frame OBJ + EXR files in a zip; or "
                "`usd`, one USD point cache (binary crate `.usd`: the mesh's topology and "
                "`st` UVs once, float32 `points` time-sampled per frame at time codes 0…F-1, "
                "`timeCodesPerSecond` the input's fps or 30). `usd` needs `mesh` or "
                "`mesh_detailed` in the outputs; with maps (or both meshes) the artifact is a "
                "zip of `performance.usd` / `performance_detailed.usd` and the per-frame EXR "
                "maps (`frame_0000_displacement.exr`, ...) that its UsdPreviewSurface reads, "
                "plus `clamped.csv`."))] = "npz",
        rig: RigQuery = None,
        marker_filter_frames: Annotated[
            Annotated[float, Field(ge=0, le=MAX_SIGMA_FRAMES, allow_inf_nan=False)]
            | Literal["auto"], Query(description=(
                "Smooth the markers in time before synthesis (marker-driven kinds): σ in "
                "frames of a Gaussian-weighted local quadratic fit over the whole "
                "performance, in a head-aligned frame (each frame's pose is kept), robust to "
                "occlusion (a gap of up to ⌈σ⌉ frames is filled, a "
                "longer one left to the thin shell's completion). 0 (default) is off; 3 "
                "frames at 30 fps cut σ = 0.3 mm marker noise reaching the surface by more "
                "than half at < 2 % cost on clean markers. `auto`: the performance's noise "
                "is estimated and the window chosen per frame by Stein's unbiased risk "
                "estimate, in the modes of the model's learned marker prior where it has "
                "one (per marker otherwise, and in frames with an occluded marker): clean "
                "markers are kept as they are, what the face rarely moves is smoothed "
                "widely, a fast onset narrowly. The frames' reported confidence reads the "
                "noise of the markers as sent, before the filter. Not for mesh input."))] = 0.0,
) -> schemas.JobAccepted:
    """Queue the synthesis of a whole performance; answers 202 with `{job_id}` and
    `Location`. The job's result is an artifact (`GET /v1/artifacts/{id}`)."""
    kind = bodies.require_media_type(request, JOB_INPUT_TYPES + (uploads.MULTIPART,))
    filename = None
    if kind == uploads.MULTIPART:
        filename, data = await bodies.read_file_part(request, "file")
    else:
        _, data = await bodies.read_body(request, JOB_INPUT_TYPES)
    job = await run_in_threadpool(
        lambda: operations.submit_synthesis_job(
            services, submit, model_id, kind, data, filename,
            outputs=parse_outputs(outputs) or DEFAULT_OUTPUTS,
            result_format=result_format, clamp=clamp, rig=rig,
            marker_filter_frames=marker_filter_frames))
    set_job_location(response, job.id)
    return schemas.JobAccepted(job_id=job.id)
