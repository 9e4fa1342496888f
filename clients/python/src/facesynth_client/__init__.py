"""facesynth-client: the Python SDK of the facesynth HTTP API (version 1).

Depends on httpx and numpy only. :class:`Client` is synchronous, :class:`AsyncClient`
asynchronous; both mirror the API's resources (``client.actors``, ``client.clips``,
``client.rigs``, ``client.models``, ``client.synthesis``, ``client.jobs``,
``client.artifacts``, ``client.tracking``) and return small dataclasses
(:class:`Actor`, :class:`Model`, :class:`Job`, ...) or dicts of NumPy arrays.

The real-time gRPC stream (``facesynth.v1.Synthesis/StreamSynthesize``) is the optional
extra ``facesynth-client[grpc]``: :class:`StreamingClient` and :class:`AsyncStreamingClient`
of :mod:`facesynth_client.streaming`, imported (with grpcio) only when first used.

Examples
--------
>>> from facesynth_client import Client
>>> fs = Client()            # $FACESYNTH_URL or http://127.0.0.1:8000, $FACESYNTH_TOKEN
>>> fs.base_url
'http://127.0.0.1:8000'
>>> fs.close()
"""

__version__ = "0.1.0"

from .arrays import load_npz, npz_bytes  # noqa: E402
from .client import AsyncClient, Client  # noqa: E402
from .errors import (ApiError, BadRequest, Conflict, FacesynthError, Forbidden,  # noqa: E402
                     IntegrityError, JobCancelled, JobError, JobFailed, MethodNotAllowed,
                     NotAcceptable, NotFound, Overloaded, PayloadTooLarge, RangeNotSatisfiable,
                     ServerError, TransportError, Unauthorized, Unprocessable,
                     UnsupportedMediaType, WaitTimeout)
from .types import (Actor, Artifact, Clip, ClipFrame, ErrorInfo, InputRig, Job,  # noqa: E402
                    JobAccepted, JobResult, KindInfo, MapInfo, MarkersInfo, Model, ModelAccepted,
                    NeutralInfo, Readiness, RigAccepted)

__all__ = [
    "Client", "AsyncClient", "npz_bytes", "load_npz",
    "Actor", "Artifact", "Clip", "ClipFrame", "ErrorInfo", "InputRig", "Job", "JobAccepted",
    "JobResult", "KindInfo", "MapInfo", "MarkersInfo", "Model", "ModelAccepted", "NeutralInfo",
    "Readiness", "RigAccepted",
    "FacesynthError", "ApiError", "BadRequest", "Unauthorized", "Forbidden", "NotFound",
    "MethodNotAllowed", "NotAcceptable", "Conflict", "PayloadTooLarge", "UnsupportedMediaType",
    "RangeNotSatisfiable", "Unprocessable", "ServerError", "Overloaded", "TransportError",
    "JobError", "JobFailed", "JobCancelled", "WaitTimeout", "IntegrityError",
    "StreamingClient", "AsyncStreamingClient",
]

#: names served by the optional gRPC extra (facesynth_client.streaming), imported on first use
_STREAMING = ("StreamingClient", "AsyncStreamingClient")


def __getattr__(name: str):
    if name in _STREAMING:
        from . import streaming

        return getattr(streaming, name)
    raise AttributeError(f"module 'facesynth_client' has no attribute {name!r}")
