"""The resource and request models of the API contract (API.md), with examples for OpenAPI.

The operations (:mod:`service.app.operations`) return them and the routes serialize them;
the HTTP-only problem body is :class:`service.api.schemas.Problem`.

Responses are built from the store's rows with ``model_validate`` (``from_attributes``);
request models forbid unknown fields, so a misspelt field is a 422 naming it.
"""

from __future__ import annotations

import json
from datetime import datetime
from typing import Annotated, Any, Literal

from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator

from service.app.limits import METADATA_MAX_BYTES
from service.methods.outputs import Output

JobStatus = Literal["queued", "running", "succeeded", "failed", "cancelled"]
#: ``cancelled`` (added in API 1, additive): the training job was cancelled. The store keeps
#: such a model ``failed`` with the error code ``cancelled``; the API reports it as
#: ``cancelled`` (see :class:`Model`) and ``?status=`` filters by the reported status.
ModelStatus = Literal["training", "ready", "failed", "cancelled"]
ResultFormat = Literal["npz", "obj-exr-zip", "usd"]
#: an input rig's name (the ``{rig}`` of ``/input-rigs/{rig}``, the ``rig`` of synthesis)
RIG_NAME_PATTERN = r"^[A-Za-z0-9][A-Za-z0-9._-]{0,63}$"

_ACTOR_ID = "act_01jb3k5q8m2v7c4x6b1n0r8tea"
_MODEL_ID = "mdl_01jb3k9w2d5f7h3k6m8p0r2tvb"
_JOB_ID = "job_01jb3k9w2e0a4c6e8g1j3m5p7r"
_CLIP_ID = "clp_01jb3k7y4b6d8f0h2k4m6p8r0t"
_CREATED = "2025-01-15T09:30:00Z"


class ErrorRecord(BaseModel):
    """Why a job or model failed."""

    code: str = Field(examples=["invalid_input"])
    message: str = Field(examples=["training needs at least one clip"])


# ---------------------------------------------------------------------------- actors
class ActorCreate(BaseModel):
    """A new actor."""

    model_config = ConfigDict(extra="forbid",
                              json_schema_extra={"examples": [{"name": "Ada",
                                                               "metadata": {"session": "2025-01"}}]})

    name: str = Field(min_length=1, max_length=200, pattern=r"^[^\x00-\x1f\x7f]+$",
                      description="Display name (no control characters).")
    metadata: dict[str, Any] = Field(default_factory=dict,
                                     description="Free-form JSON metadata (at most 64 KiB).")

    @field_validator("name")
    @classmethod
    def _encodable_name(cls, value: str) -> str:
        from service.app.validation import check_text

        return check_text(value, "the actor name")

    @field_validator("metadata")
    @classmethod
    def _bounded(cls, value: dict[str, Any]) -> dict[str, Any]:
        from service.app.validation import check_json_text

        check_json_text(value, "metadata")       # before json.dumps, which would accept it
        size = len(json.dumps(value, allow_nan=False).encode())
        if size > METADATA_MAX_BYTES:
            raise ValueError(f"metadata is {size} bytes as JSON, more than {METADATA_MAX_BYTES}")
        return value


class Actor(BaseModel):
    """An actor and what has been uploaded for it."""

    model_config = ConfigDict(from_attributes=True, json_schema_extra={"examples": [{
        "id": _ACTOR_ID, "name": "Ada", "metadata": {}, "created_at": _CREATED,
        "vertex_count": 40962, "triangle_count": 81920, "marker_count": 150}]})

    id: str
    name: str
    metadata: dict[str, Any] = Field(validation_alias="meta")
    created_at: datetime
    vertex_count: int | None = Field(None, description="Vertices of the neutral (null before "
                                                       "PUT /neutral).")
    triangle_count: int | None = None
    marker_count: int | None = Field(None, description="Markers of the layout (null before "
                                                       "PUT /markers).")


class NeutralInfo(BaseModel):
    """What was stored of an uploaded neutral."""

    model_config = ConfigDict(json_schema_extra={"examples": [{
        "vertex_count": 40962, "triangle_count": 81920, "uv_seams": 812, "polygons_split": 0,
        "regions": []}]})

    vertex_count: int
    triangle_count: int
    uv_seams: int = Field(description="Vertices on UV seams (vertices with more than one UV).")
    polygons_split: int = Field(description="Polygons with more than three corners that were "
                                            "split into triangles (fans (a,b,c),(a,c,d),...).")
    regions: list[str] = Field(default_factory=list,
                               description="Names of the `region_<name>` vertex sets stored.")


class LayoutMarker(BaseModel):
    """One marker of a layout: exactly one of `vertex`, `triangle`+`barycentric`, `position`."""

    name: str
    vertex: int | None = Field(None, ge=0)
    triangle: int | None = Field(None, ge=0)
    barycentric: list[float] | None = Field(None, min_length=3, max_length=3)
    position: list[float] | None = Field(None, min_length=3, max_length=3,
                                         description="Snapped to the nearest surface point.")


class MarkerLayout(BaseModel):
    """A marker layout (API.md `PUT /markers`)."""

    model_config = ConfigDict(json_schema_extra={"examples": [{"markers": [
        {"name": "FH1", "vertex": 812},
        {"name": "FH2", "triangle": 9912, "barycentric": [0.2, 0.3, 0.5]},
        {"name": "FH3", "position": [12.5, 80.1, 95.0]}]}]})

    markers: list[LayoutMarker] = Field(min_length=1)


class MarkersInfo(BaseModel):
    """The stored layout."""

    model_config = ConfigDict(json_schema_extra={"examples": [{
        "marker_count": 150, "snapped": 1, "max_snap_distance": 0.42}]})

    marker_count: int
    snapped: int = Field(description="Markers given as positions, snapped to the surface.")
    max_snap_distance: float = Field(description="Farthest snap, in the actor's unit.")
    renormalized: int = Field(0, description=(
        "Markers whose barycentric coordinates were within 1e-4 of summing to 1 (or of 0) but "
        "not exactly, and were clipped at 0 and renormalized (e.g. a layout written with 6 "
        "decimals)."))


# ---------------------------------------------------------------------------- clips
class Clip(BaseModel):
    """A stored clip."""

    model_config = ConfigDict(from_attributes=True, json_schema_extra={"examples": [{
        "clip_id": _CLIP_ID, "actor_id": _ACTOR_ID, "name": "smile", "frames": 120,
        "size_bytes": 59000000, "created_at": _CREATED}]})

    clip_id: str = Field(validation_alias="id")
    actor_id: str
    name: str | None
    frames: int
    size_bytes: int
    created_at: datetime


class ClipAdded(Clip):
    """A clip just stored, with what its files' readers accepted that you should know."""

    model_config = ConfigDict(from_attributes=True, json_schema_extra={"examples": [{
        "clip_id": _CLIP_ID, "actor_id": _ACTOR_ID, "name": "smile", "frames": 120,
        "size_bytes": 59000000, "created_at": _CREATED,
        "notes": ["the TRC header says NumFrames 121 but the file has 120 frame rows; the "
                  "120 rows were read"]}]})

    notes: list[str] = Field(default_factory=list, description=(
        "What the marker file's reader accepted but did not read as the file declares it "
        "(e.g. a TRC whose `NumFrames` disagrees with its frame rows: the rows are read); "
        "empty when every file read exactly as declared."))


# ---------------------------------------------------------------------------- rigs
class InputRig(BaseModel):
    """An input rig and its registration state."""

    model_config = ConfigDict(from_attributes=True)

    rig_id: str = Field(validation_alias="id")
    actor_id: str
    name: str
    status: Literal["registering", "ready", "failed"]
    error: ErrorRecord | None = None
    created_at: datetime


class RigAccepted(BaseModel):
    """An input rig stored, its registration queued."""

    model_config = ConfigDict(json_schema_extra={"examples": [{
        "rig_id": "rig_01jb3kaa1b2c3d4e5f6g7h8j9k", "name": "game-lod2", "job_id": _JOB_ID,
        "vertex_count": 4012, "triangle_count": 8000, "landmarks": 12}]})

    rig_id: str
    name: str
    job_id: str
    vertex_count: int
    triangle_count: int
    landmarks: int


# ---------------------------------------------------------------------------- models
class ModelAccepted(BaseModel):
    """A model created in status `training`, with its queued training job."""

    model_config = ConfigDict(json_schema_extra={"examples": [{"model_id": _MODEL_ID,
                                                               "job_id": _JOB_ID}]})

    model_id: str
    job_id: str


class Model(BaseModel):
    """A model (API.md `GET /v1/models/{model_id}`)."""

    model_config = ConfigDict(from_attributes=True, json_schema_extra={"examples": [{
        "id": _MODEL_ID, "actor_id": _ACTOR_ID, "kind": "pdm", "status": "ready",
        "params": {"order": "biquadratic", "medium_resolution": 512, "fine_resolution": 1024,
                   "ridge": 0.1},
        "metrics": {"training_frames": 480}, "created_at": _CREATED, "size_bytes": 310000000}]})

    id: str
    actor_id: str
    kind: str
    status: ModelStatus = Field(description=(
        "`training` until its training job ends, then `ready`, `failed` (see `error`) or "
        "`cancelled` (the training job was cancelled; `error.code` is `cancelled`). "
        "`cancelled` is a value added to API 1: treat unknown values as not ready."))
    params: dict[str, Any]
    metrics: dict[str, Any] | None = Field(None, description="Training fit errors.")
    created_at: datetime
    size_bytes: int | None = None
    error: ErrorRecord | None = None

    @model_validator(mode="after")
    def _cancelled(self) -> "Model":
        """A model whose training was cancelled (stored ``failed`` with error code
        ``cancelled``) is reported ``cancelled``."""
        if self.status == "failed" and self.error is not None and self.error.code == "cancelled":
            self.status = "cancelled"
        return self


class MapInfo(BaseModel):
    """A UV-space map of a model, an EXR file."""

    model_config = ConfigDict(json_schema_extra={"examples": [{
        "name": "fine", "channels": ["n.a0", "n.a1", "n.a2", "n.a3", "n.a4", "n.a5"],
        "width": 1024, "height": 1024, "size_bytes": 25165824,
        "url": f"/v1/models/{_MODEL_ID}/maps/fine.exr"}]})

    name: str
    channels: list[str]
    width: int
    height: int
    size_bytes: int
    url: str


class KindInfo(BaseModel):
    """A model kind and its training parameters."""

    name: str
    title: str
    description: str
    input: Literal["markers", "meshes"]
    params_schema: dict[str, Any] = Field(description="JSON Schema of `params`, with defaults.")


# ---------------------------------------------------------------------------- synthesis
class SynthesizeBody(BaseModel):
    """JSON body of `POST /synthesize` (an `.npz` with `markers` is the compact alternative)."""

    model_config = ConfigDict(extra="forbid", json_schema_extra={"examples": [{
        "markers": [[[12.1, 80.3, 95.2], None, [3.0, 61.9, 101.4]]],
        "outputs": ["mesh", "displacement"]}]})

    markers: list[list[list[float | None] | None]] = Field(
        min_length=1, description="(F,M,3) world-space positions in layout order; `null` for "
                                  "an occluded marker.")
    outputs: list[Output] | None = Field(
        None, description="What to return (default `mesh`, `displacement`); overrides the "
                          "`outputs` query parameter.")
    map_resolution: int | None = Field(
        None, ge=16, description="Side of the returned maps in texels (default: the model's); "
                                 "at most the server's `max_map_resolution`.")
    clamp: bool = Field(True, description="Limit extrapolation beyond the training data.")


class ClipFrameRef(BaseModel):
    """A keyframe given as a frame of one of the actor's clips (on the actor's topology)."""

    model_config = ConfigDict(extra="forbid", json_schema_extra={"examples": [
        {"clip_id": _CLIP_ID, "frame": 12}]})

    clip_id: str = Field(description="Id of a clip of the model's actor.")
    frame: int = Field(ge=0, description="0-based frame index within the clip.")


Vertex = Annotated[list[float], Field(min_length=3, max_length=3)]


class RetimeBody(BaseModel):
    """JSON body of `POST /retime` (an `.npz` with `keyframes` (K,v,3) and query parameters
    is the compact alternative)."""

    model_config = ConfigDict(extra="forbid", json_schema_extra={"examples": [
        {"keyframes": [{"clip_id": _CLIP_ID, "frame": 0}, {"clip_id": _CLIP_ID, "frame": 19}],
         "length": 24, "extend_to_full_motion": False},
        {"keyframes": [[[12.1, 80.3, 95.2], [12.9, 80.1, 95.6], [13.4, 79.8, 95.9]],
                       [[12.0, 79.1, 95.2], [12.8, 79.0, 95.7], [13.5, 78.7, 96.0]]],
         "length": 30, "extend_to_full_motion": True, "rig": "game-lod2"}]})

    keyframes: list[list[Vertex] | ClipFrameRef] = Field(
        min_length=2,
        description="Two or more keyframes, in order: each the vertices [[x,y,z], ...] of a "
                    "frame (on the actor's topology, or on the input rig's with `rig`), or "
                    "a clip frame `{clip_id, frame}` of the model's actor. With K keyframes, "
                    "keyframe k is output frame round(k (length-1)/(K-1)).")
    length: int = Field(ge=2, description="Output frames m, keyframes included (m >= K; at "
                                          "most the server's `max_frames_per_request`).")
    extend_to_full_motion: bool = Field(
        False, description="Extend each matched database subsequence to the full motion "
                           "(bermano2014 §6.2) instead of only the keyframes' span.")
    rig: str | None = Field(None, pattern=RIG_NAME_PATTERN,
                            description="The registered input rig the vertex keyframes are "
                                        "on (also accepted as a query parameter).")


# ---------------------------------------------------------------------------- jobs
class JobAccepted(BaseModel):
    """A queued job."""

    model_config = ConfigDict(json_schema_extra={"examples": [{"job_id": _JOB_ID}]})

    job_id: str


class JobResult(BaseModel):
    """What a succeeded job produced."""

    model_config = ConfigDict(extra="allow")

    model_id: str | None = None
    artifact_ids: list[str] | None = None


class Job(BaseModel):
    """A job (API.md `GET /v1/jobs/{job_id}`)."""

    model_config = ConfigDict(from_attributes=True, json_schema_extra={"examples": [{
        "id": _JOB_ID, "kind": "train", "status": "running", "progress": 0.42,
        "stage": "fine band", "actor_id": _ACTOR_ID, "model_id": _MODEL_ID,
        "created_at": _CREATED, "started_at": _CREATED, "finished_at": None}]})

    id: str
    kind: str
    status: JobStatus
    progress: float = Field(ge=0, le=1)
    stage: str
    actor_id: str
    model_id: str | None = None
    created_at: datetime
    started_at: datetime | None = None
    finished_at: datetime | None = None
    error: ErrorRecord | None = None
    result: JobResult | None = None


class Artifact(BaseModel):
    """A downloadable job result."""

    model_config = ConfigDict(from_attributes=True)

    id: str
    job_id: str
    media_type: str
    filename: str | None
    size_bytes: int
    sha256: str
    created_at: datetime


class Items(BaseModel):
    """Base of list responses: ``{"items": [...], "next_cursor": ...}``.

    A list answers one page (``limit`` items at most); ``next_cursor`` is set when more
    follow, to be sent back as ``cursor`` (``service/api/query.py``)."""

    next_cursor: str | None = Field(
        default=None, description="Set when more items follow: send it back as `cursor` for "
                                  "the next page; absent or null on the last page.")


class ActorList(Items):
    items: list[Actor]


class ClipList(Items):
    items: list[Clip]


class RigList(Items):
    items: list[InputRig]


class ModelList(Items):
    items: list[Model]


class MapList(Items):
    items: list[MapInfo]


class KindList(Items):
    items: list[KindInfo]


class JobList(Items):
    items: list[Job]


class ArtifactList(Items):
    items: list[Artifact]
