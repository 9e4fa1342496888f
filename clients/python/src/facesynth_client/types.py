"""Typed results: small dataclasses parsed from the server's JSON.

Each has ``from_json(dict)`` (unknown fields are kept in ``raw`` and otherwise ignored, so a
newer server does not break an older client) and compares by value without ``raw``.
Timestamps are timezone-aware :class:`datetime.datetime`.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from datetime import datetime
from typing import Any, Callable, Mapping, TypeVar

__all__ = [
    "Actor", "NeutralInfo", "MarkersInfo", "Clip", "InputRig", "RigAccepted", "Model",
    "ModelAccepted", "MapInfo", "KindInfo", "JobAccepted", "ErrorInfo", "JobResult", "Job",
    "Artifact", "Readiness", "ClipFrame", "JOB_FINAL_STATUSES", "Scan",
]

#: job statuses after which nothing changes
JOB_FINAL_STATUSES = ("succeeded", "failed", "cancelled")

T = TypeVar("T", bound="_Parsed")


def parse_datetime(value: Any) -> datetime | None:
    """An ISO 8601 timestamp (``...Z`` or with an offset) as a datetime; None stays None."""
    if value is None or isinstance(value, datetime):
        return value
    text = str(value)
    if text.endswith(("Z", "z")):
        text = text[:-1] + "+00:00"
    return datetime.fromisoformat(text)


def _raw() -> Any:
    return field(default_factory=dict, repr=False, compare=False)


def _conv(fn: Callable[[Any], Any]) -> dict:
    return {"parse": fn}


class _Parsed:
    """``from_json`` for the dataclasses below: each field from the key of its name (or its
    ``key`` metadata), converted by its ``parse`` metadata."""

    @classmethod
    def from_json(cls: type[T], data: Mapping[str, Any]) -> T:
        values: dict[str, Any] = {}
        for f in dataclasses.fields(cls):  # type: ignore[arg-type]
            if f.name == "raw":
                continue
            key = f.metadata.get("key", f.name)
            if key not in data:
                continue
            value = data[key]
            parse = f.metadata.get("parse")
            values[f.name] = parse(value) if parse is not None and value is not None else value
        return cls(**values, raw=dict(data))  # type: ignore[call-arg]


_DT = _conv(parse_datetime)


@dataclass
class Actor(_Parsed):
    """An actor (``GET /v1/actors/{actor_id}``): counts are None until uploaded."""

    id: str
    name: str
    created_at: datetime | None = field(default=None, metadata=_DT)
    metadata: dict[str, Any] = field(default_factory=dict)
    vertex_count: int | None = None
    triangle_count: int | None = None
    marker_count: int | None = None
    raw: dict[str, Any] = _raw()


@dataclass
class NeutralInfo(_Parsed):
    """What the server stored of an uploaded neutral (``PUT .../neutral``)."""

    vertex_count: int
    triangle_count: int
    uv_seams: int = 0
    polygons_split: int = 0
    regions: list[str] = field(default_factory=list)
    raw: dict[str, Any] = _raw()


@dataclass
class MarkersInfo(_Parsed):
    """The stored marker layout (``PUT .../markers``); ``max_snap_distance`` in the actor's
    unit."""

    marker_count: int
    snapped: int = 0
    max_snap_distance: float = 0.0
    raw: dict[str, Any] = _raw()


@dataclass
class Clip(_Parsed):
    """A stored clip of an actor.

    ``notes`` (uploads only): what the server's marker reader accepted but did not read as
    the file declares it, e.g. a TRC whose ``NumFrames`` disagrees with its rows; empty
    otherwise.
    """

    clip_id: str
    frames: int
    actor_id: str | None = None
    name: str | None = None
    size_bytes: int | None = None
    created_at: datetime | None = field(default=None, metadata=_DT)
    notes: list[str] = field(default_factory=list)
    raw: dict[str, Any] = _raw()

    @property
    def id(self) -> str:
        return self.clip_id


@dataclass
class ErrorInfo(_Parsed):
    """Why a job, a model or a rig registration failed."""

    code: str
    message: str
    raw: dict[str, Any] = _raw()


_ERR = _conv(ErrorInfo.from_json)


@dataclass
class InputRig(_Parsed):
    """An input rig and its registration state (``registering``, ``ready``, ``failed``)."""

    rig_id: str
    name: str
    status: str
    actor_id: str | None = None
    error: ErrorInfo | None = field(default=None, metadata=_ERR)
    created_at: datetime | None = field(default=None, metadata=_DT)
    raw: dict[str, Any] = _raw()


@dataclass
class RigAccepted(_Parsed):
    """An input rig stored, its registration queued as job ``job_id``."""

    rig_id: str
    name: str
    job_id: str
    vertex_count: int = 0
    triangle_count: int = 0
    landmarks: int = 0
    raw: dict[str, Any] = _raw()


@dataclass
class Model(_Parsed):
    """A model (``GET /v1/models/{model_id}``); ``metrics`` holds the training fit errors."""

    id: str
    actor_id: str
    kind: str
    status: str
    params: dict[str, Any] = field(default_factory=dict)
    metrics: dict[str, Any] | None = None
    created_at: datetime | None = field(default=None, metadata=_DT)
    size_bytes: int | None = None
    error: ErrorInfo | None = field(default=None, metadata=_ERR)
    raw: dict[str, Any] = _raw()

    @property
    def ready(self) -> bool:
        return self.status == "ready"


@dataclass
class ModelAccepted(_Parsed):
    """A model created in status ``training``, trained by job ``job_id``."""

    model_id: str
    job_id: str
    raw: dict[str, Any] = _raw()


@dataclass
class MapInfo(_Parsed):
    """A UV-space map of a model (an EXR file of ``width`` × ``height`` texels)."""

    name: str
    channels: list[str] = field(default_factory=list)
    width: int = 0
    height: int = 0
    size_bytes: int = 0
    url: str = ""
    raw: dict[str, Any] = _raw()


@dataclass
class KindInfo(_Parsed):
    """A model kind the server trains; ``params_schema`` is the JSON Schema of its
    training ``params`` (with defaults)."""

    name: str
    title: str = ""
    description: str = ""
    input: str = ""
    params_schema: dict[str, Any] = field(default_factory=dict)
    raw: dict[str, Any] = _raw()


@dataclass
class JobAccepted(_Parsed):
    """A queued job (a 202 answer); ``location`` is the job's URL path."""

    job_id: str
    location: str | None = None
    raw: dict[str, Any] = _raw()


@dataclass
class JobResult(_Parsed):
    """What a succeeded job produced: a model, artifacts, or more (kept in ``raw``)."""

    model_id: str | None = None
    artifact_ids: list[str] = field(default_factory=list)
    raw: dict[str, Any] = _raw()


@dataclass
class Job(_Parsed):
    """A job (``GET /v1/jobs/{job_id}``).

    Attributes
    ----------
    status : str      ``queued``, ``running``, ``succeeded``, ``failed`` or ``cancelled``
    progress : float  0..1
    stage : str       what it is doing, for a person
    error : ErrorInfo or None   why it failed
    result : JobResult or None  what it produced once succeeded
    """

    id: str
    kind: str
    status: str
    progress: float = 0.0
    stage: str = ""
    actor_id: str | None = None
    model_id: str | None = None
    created_at: datetime | None = field(default=None, metadata=_DT)
    started_at: datetime | None = field(default=None, metadata=_DT)
    finished_at: datetime | None = field(default=None, metadata=_DT)
    error: ErrorInfo | None = field(default=None, metadata=_ERR)
    result: JobResult | None = field(default=None, metadata=_conv(JobResult.from_json))
    raw: dict[str, Any] = _raw()

    @property
    def done(self) -> bool:
        """Whether the job ended (succeeded, failed or cancelled)."""
        return self.status in JOB_FINAL_STATUSES

    @property
    def artifact_ids(self) -> list[str]:
        """The ids of the job's result artifacts (empty before it succeeded)."""
        return list(self.result.artifact_ids) if self.result else []

    @property
    def job_id(self) -> str:
        return self.id


@dataclass
class Artifact(_Parsed):
    """A downloadable job result; ``sha256`` is also its ETag."""

    id: str
    job_id: str
    media_type: str = "application/octet-stream"
    filename: str | None = None
    size_bytes: int = 0
    sha256: str = ""
    created_at: datetime | None = field(default=None, metadata=_DT)
    raw: dict[str, Any] = _raw()


@dataclass
class Readiness(_Parsed):
    """``GET /readyz``: ``status`` ``ok`` or ``unavailable`` and each component's check."""

    status: str
    checks: dict[str, str] = field(default_factory=dict)
    raw: dict[str, Any] = _raw()

    @property
    def ready(self) -> bool:
        return self.status == "ok"


@dataclass(frozen=True)
class ClipFrame:
    """A retime keyframe given as frame ``frame`` (0-based) of clip ``clip_id`` of the
    model's actor."""

    clip_id: str
    frame: int

    def to_json(self) -> dict[str, Any]:
        return {"clip_id": self.clip_id, "frame": int(self.frame)}


@dataclass
class Scan(_Parsed):
    """A stored scan of an actor: UV-space maps of ``width`` × ``height`` texels."""

    scan_id: str
    width: int
    height: int
    maps: list[str] = field(default_factory=list)
    actor_id: str | None = None
    name: str | None = None
    size_bytes: int | None = None
    created_at: datetime | None = field(default=None, metadata=_DT)
    raw: dict[str, Any] = _raw()

    @property
    def id(self) -> str:
        return self.scan_id
