"""Real-time synthesis over gRPC: ``facesynth.v1.Synthesis/StreamSynthesize``.

A live marker stream in, one detailed mesh (and the asked maps) out per frame, in order. Needs
the optional extra: ``pip install 'facesynth-client[grpc]'`` (grpcio and protobuf); the rest of
the SDK does not. The stubs are generated from the server's ``synthesis.proto`` into
:mod:`facesynth_client._proto` (``python -m service.grpc.generate`` writes both copies), so
the SDK never imports the server.

:class:`StreamingClient` (sync) and :class:`AsyncStreamingClient` (``grpc.aio``) share one
core, :class:`StreamPlan`: the first message's fields, the encoding of marker frames, the
decoding of replies and the mapping of gRPC status codes to the SDK's errors. Both pipeline:
frames are sent ahead of the replies, at most ``max_in_flight`` unanswered at any time (a
frame is taken from the source only once it has a slot), so the network and the server's work
overlap while a slow consumer holds back a fast source (no unbounded buffering, no stale
frames of a live source waiting in a queue).

Examples
--------
>>> from facesynth_client.streaming import StreamingClient
>>> with StreamingClient("127.0.0.1:50051", token="s3cret") as stream:     # doctest: +SKIP
...     for out in stream.synthesize(model_id, live_markers(), outputs=("mesh", "displacement")):
...         show(out["frame"], out["vertices"], out["displacement"])     # (V,3), (H,W) float32
"""

from __future__ import annotations

import asyncio
import os
import threading
from dataclasses import dataclass, field
from typing import Any, AsyncIterable, AsyncIterator, Iterable, Iterator, Sequence

import numpy as np

from . import errors

try:
    import grpc
    import grpc.aio
    from google.protobuf.descriptor import FieldDescriptor
except ImportError as error:  # pragma: no cover - depends on the installation
    raise ImportError("facesynth_client.streaming needs grpcio and protobuf: "
                      "pip install 'facesynth-client[grpc]'") from error

from ._proto.facesynth.v1 import synthesis_pb2 as pb

__all__ = ["StreamingClient", "AsyncStreamingClient", "StreamPlan", "OUTPUTS",
           "DEFAULT_OUTPUTS", "DEFAULT_TARGET", "DEFAULT_IN_FLIGHT", "MAX_MESSAGE_BYTES",
           "channel_options", "stream_error"]

#: the outputs a stream may ask for (synthesis.proto's MarkerFrame.outputs)
OUTPUTS = ("mesh", "mesh_detailed", "displacement", "albedo", "normal_map")
#: what a stream computes when it asks for nothing (the server's default)
DEFAULT_OUTPUTS = ("mesh",)
#: the server's address when neither ``target`` nor ``$FACESYNTH_GRPC`` is given
DEFAULT_TARGET = "127.0.0.1:50051"
#: frames sent and not yet answered, at most (the pipeline's depth). The server synthesizes a
#: stream's frames on its synthesis threads side by side (one per core by default) and takes
#: up to threads + 1 of them: on two cores 3 keeps both threads busy while a reply travels;
#: more adds latency, not throughput. Level-1 PDM, loopback, the shared 2-core machine at
#: load 14-16 (benchmarks/grpc_stream.py, 80 frames, two alternating runs, medians): mesh
#: depth 1/2/3/4 30.6/32.6/33.1/34.8 frames/s, round trip 31/55/89/109 ms; mesh + both maps
#: 6.0/7.2/8.5/7.8 frames/s, 182/270/323/469 ms.
DEFAULT_IN_FLIGHT = 3
#: message size limit, both directions: a reply with 1024² displacement, albedo and normal
#: maps is 28 MiB plus the meshes (gRPC's default of 4 MiB is too small); the server's too
MAX_MESSAGE_BYTES = 64 * 2**20

F32 = np.dtype("<f4")
F16 = np.dtype("<f2")
I32 = np.dtype("<i4")
#: MeshFrame byte fields of mesh outputs, and its Map fields (the output names)
MESH_FIELDS = ("vertices", "vertices_detailed")
MAP_FIELDS = ("displacement", "albedo", "normal_map")
#: gRPC status → (SDK error, the HTTP status it stands for), as synthesis.proto lists them
_STATUS_ERRORS = {
    "NOT_FOUND": (errors.NotFound, 404),
    "INVALID_ARGUMENT": (errors.Unprocessable, 422),
    "FAILED_PRECONDITION": (errors.Conflict, 409),
    "UNAUTHENTICATED": (errors.Unauthorized, 401),
    "PERMISSION_DENIED": (errors.Forbidden, 403),
    "RESOURCE_EXHAUSTED": (errors.Overloaded, 503),
}
#: gRPC statuses of a server that could not be reached or a stream that broke
_TRANSPORT_CODES = frozenset({"UNAVAILABLE", "DEADLINE_EXCEEDED", "CANCELLED"})


def channel_options(max_message_bytes: int = MAX_MESSAGE_BYTES) -> list[tuple[str, int]]:
    """Channel options that send and accept messages up to ``max_message_bytes``."""
    return [("grpc.max_receive_message_length", max_message_bytes),
            ("grpc.max_send_message_length", max_message_bytes)]


def stream_error(error: grpc.RpcError) -> errors.FacesynthError:
    """The SDK error of a gRPC status, to catch by meaning as over HTTP: NOT_FOUND →
    :class:`~facesynth_client.NotFound`, INVALID_ARGUMENT → ``Unprocessable``,
    FAILED_PRECONDITION → ``Conflict``, UNAUTHENTICATED → ``Unauthorized``,
    RESOURCE_EXHAUSTED → ``Overloaded``; UNAVAILABLE / DEADLINE_EXCEEDED →
    ``TransportError``; others a ``ServerError``. ``.problem["grpc_status"]`` names the code."""
    code = error.code() if callable(getattr(error, "code", None)) else None
    name = getattr(code, "name", "UNKNOWN")
    details = (error.details() if callable(getattr(error, "details", None)) else None) or str(error)
    if name in _TRANSPORT_CODES:
        return errors.TransportError(f"gRPC stream: {name}: {details}")
    cls, status = _STATUS_ERRORS.get(name, (errors.ServerError, 500))
    return cls({"type": f"urn:facesynth:grpc:{name.lower()}", "title": name, "status": status,
                "detail": details, "grpc_status": name})


_SERVICE = pb.DESCRIPTOR.services_by_name["Synthesis"]
#: the streaming method's path, whose replies the clients take as bytes (:func:`decode_reply`)
_METHOD = f"/{_SERVICE.full_name}/{_SERVICE.methods_by_name['StreamSynthesize'].name}"
#: wire type of each field type MeshFrame and Map use
#: (https://protobuf.dev/programming-guides/encoding/: 0 varint, 1 64-bit, 2 length-delimited,
#: 5 32-bit)
_WIRE_TYPES = {FieldDescriptor.TYPE_UINT32: 0, FieldDescriptor.TYPE_BOOL: 0,
               FieldDescriptor.TYPE_DOUBLE: 1, FieldDescriptor.TYPE_BYTES: 2,
               FieldDescriptor.TYPE_MESSAGE: 2, FieldDescriptor.TYPE_FLOAT: 5}


def _wire_layout(message: Any) -> dict[int, tuple[str, int]]:
    """Field number → (name, wire type) of a message, from its generated descriptor."""
    return {f.number: (f.name, _WIRE_TYPES[f.type]) for f in message.DESCRIPTOR.fields}


_MESH_FRAME = _wire_layout(pb.MeshFrame)
_MAP = _wire_layout(pb.Map)


def _wire_fields(data: memoryview, layout: dict[int, tuple[str, int]]) -> dict[str, Any] | None:
    """The known fields of one message's wire encoding by name: ints for varints, views of
    ``data`` for the rest; unknown fields skipped. None where the plain parser must decide
    (a field repeated, which protobuf merges, one of an unexpected wire type, or a truncated
    message, which it refuses)."""
    out: dict[str, Any] = {}
    pos, end = 0, len(data)
    while pos < end:
        key, pos = _varint(data, pos)
        if pos < 0:
            return None
        number, wire = key >> 3, key & 7
        if wire == 0:
            value, pos = _varint(data, pos)
        elif wire in (1, 5):
            size = 8 if wire == 1 else 4
            value, pos = data[pos:pos + size], pos + size
        elif wire == 2:
            size, pos = _varint(data, pos)
            value, pos = data[pos:pos + size], pos + size
        else:
            return None
        if not 0 <= pos <= end:
            return None
        if number in layout:
            name, expected = layout[number]
            if wire != expected or name in out:
                return None
            out[name] = value
    return out


def _varint(data: memoryview, pos: int) -> tuple[int, int]:
    """The varint at ``pos`` and the position after it (-1 past the end of ``data``)."""
    value = shift = 0
    while True:
        if pos >= len(data):
            return 0, -1
        byte = data[pos]
        pos += 1
        value |= (byte & 0x7F) << shift
        if byte < 0x80:
            return value, pos
        shift += 7


def _decode_wire(data: bytes) -> dict[str, Any] | None:
    """:func:`decode_reply` of a serialized MeshFrame read field by field, its arrays views of
    ``data`` (the message object would copy each array twice); None where the plain parser
    must decide."""
    view = memoryview(data)
    fields = _wire_fields(view, _MESH_FRAME)
    if fields is None:
        return None
    def number(name: str, dtype: str) -> float:
        return float(np.frombuffer(fields[name], dtype)[0]) if name in fields else 0.0

    out: dict[str, Any] = {"frame": fields.get("frame", 0), "clamped": number("clamped", "<f4"),
                           "latency_ms": number("latency_ms", "<f8")}
    count = fields.get("vertex_count", 0)
    for key in MESH_FIELDS:
        if len(fields.get(key, b"")):
            out[key] = np.frombuffer(fields[key], F32).reshape(count, 3)
    if len(fields.get("faces", b"")):
        out["faces"] = np.frombuffer(fields["faces"], I32).reshape(-1, 3)
    for key in MAP_FIELDS:
        if key in fields:
            m = _wire_fields(fields[key], _MAP)
            if m is None:
                return None
            channels = m.get("channels", 0)
            shape = (m.get("height", 0), m.get("width", 0)) + ((channels,) if channels != 1 else ())
            out[key] = np.frombuffer(m.get("data", b""), F16 if m.get("half") else F32).reshape(shape)
    return out


def decode_reply(reply: pb.MeshFrame | bytes) -> dict[str, Any]:
    """The arrays of a MeshFrame (or of its serialized bytes, as the clients receive it)
    under ``synthesize``'s keys, for the fields it carries.

    Returns
    -------
    dict
        ``frame`` int, ``clamped`` float, ``latency_ms`` float (the server's time for the
        frame), and as present: ``vertices`` / ``vertices_detailed`` (V,3) float32,
        ``faces`` (T,3) int32 (first reply only), ``displacement`` (H,W) float32,
        ``albedo`` / ``normal_map`` (H,W,3) float32 (float16 for a stream with ``half``).
        Arrays are read-only views of the message's bytes.
    """
    if isinstance(reply, (bytes, bytearray, memoryview)):
        out = _decode_wire(reply)
        if out is not None:
            return out
        reply = pb.MeshFrame.FromString(bytes(reply))
    out: dict[str, Any] = {"frame": reply.frame, "clamped": reply.clamped,
                           "latency_ms": reply.latency_ms}
    for key in MESH_FIELDS:
        data = getattr(reply, key)
        if data:
            out[key] = np.frombuffer(data, F32).reshape(reply.vertex_count, 3)
    if reply.faces:
        out["faces"] = np.frombuffer(reply.faces, I32).reshape(-1, 3)
    for key in MAP_FIELDS:
        if reply.HasField(key):
            m = getattr(reply, key)
            shape = (m.height, m.width) + ((m.channels,) if m.channels != 1 else ())
            out[key] = np.frombuffer(m.data, F16 if m.half else F32).reshape(shape)
    return out


@dataclass
class StreamPlan:
    """One stream's request side, shared by the sync and async clients.

    Parameters
    ----------
    model_id : str             the model (an id of the HTTP API)
    outputs : sequence of str  subset of :data:`OUTPUTS`
    clamp : bool or None       limit extrapolated detail (None: the server's default, true)
    start_frame : int          the number of the first frame (echoed in replies' ``frame``)
    token : str or None        bearer token, sent as ``authorization`` metadata
    half : bool                maps as float16 (half the bytes; within 2^-11 relative of
                               float32)
    """

    model_id: str
    outputs: Sequence[str] = DEFAULT_OUTPUTS
    clamp: bool | None = None
    start_frame: int = 0
    token: str | None = None
    half: bool = False
    sent: int = field(default=0, init=False)

    @property
    def metadata(self) -> list[tuple[str, str]] | None:
        return [("authorization", f"Bearer {self.token}")] if self.token else None

    def message(self, markers: Any) -> pb.MarkerFrame:
        """The next MarkerFrame: markers (M,3) in the actor's unit, NaN for occluded; the
        first also names the model, the outputs and clamp."""
        values = np.asarray(markers, dtype=np.float32)
        if values.ndim != 2 or values.shape[1] != 3:
            raise ValueError(f"frame {self.start_frame + self.sent}: markers must be (M,3), "
                             f"got shape {values.shape}")
        fields: dict[str, Any] = {}
        if self.sent == 0:
            fields = {"model_id": self.model_id, "outputs": list(self.outputs)}
            if self.clamp is not None:
                fields["clamp"] = bool(self.clamp)
            if self.half:
                fields["half"] = True
        msg = pb.MarkerFrame(frame=self.start_frame + self.sent, markers=values.ravel(),
                             marker_count=len(values), **fields)
        self.sent += 1
        return msg


def _stream_method(channel: Any) -> Any:
    """StreamSynthesize on ``channel`` (sync or ``grpc.aio``) with its replies as the bytes
    received, for :func:`decode_reply` (the stub's would parse them into a message first)."""
    return channel.stream_stream(_METHOD, request_serializer=pb.MarkerFrame.SerializeToString,
                                 response_deserializer=None)


def _check_depth(max_in_flight: int) -> int:
    if int(max_in_flight) < 1:
        raise ValueError(f"max_in_flight must be at least 1, got {max_in_flight}")
    return int(max_in_flight)


class StreamingClient:
    """The synchronous gRPC client.

    Parameters
    ----------
    target : str, optional     ``host:port``, default ``$FACESYNTH_GRPC``, else
                               ``127.0.0.1:50051``
    token : str, optional      bearer token, default ``$FACESYNTH_TOKEN``
    channel : grpc.Channel, optional   use this channel (not closed by :meth:`close`)
    credentials : grpc.ChannelCredentials, optional   TLS (e.g. through an ingress proxy)
    max_message_bytes : int    message size limit, both directions
    """

    def __init__(self, target: str | None = None, token: str | None = None, *,
                 channel: grpc.Channel | None = None,
                 credentials: grpc.ChannelCredentials | None = None,
                 max_message_bytes: int = MAX_MESSAGE_BYTES):
        self.target = target or os.environ.get("FACESYNTH_GRPC") or DEFAULT_TARGET
        self.token = token if token is not None else os.environ.get("FACESYNTH_TOKEN") or None
        self._own = channel is None
        if channel is None:
            options = channel_options(max_message_bytes)
            channel = (grpc.secure_channel(self.target, credentials, options) if credentials
                       else grpc.insecure_channel(self.target, options))
        self._channel = channel
        self._stream = _stream_method(channel)

    def close(self) -> None:
        """Close the channel made by this client (an injected one stays open)."""
        if self._own:
            self._channel.close()

    def __enter__(self) -> "StreamingClient":
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()

    def synthesize(self, model_id: str, frames: Iterable[Any],
                   outputs: Sequence[str] = DEFAULT_OUTPUTS, *, clamp: bool | None = None,
                   max_in_flight: int = DEFAULT_IN_FLIGHT, start_frame: int = 0,
                   timeout: float | None = None, half: bool = False) -> Iterator[dict[str, Any]]:
        """Stream marker frames to the server and yield its results, one per frame, in order.

        Parameters
        ----------
        model_id : str
        frames : iterable of (M,3) float   markers in the model's layout order, actor's unit,
                 NaN for occluded; pulled as the window allows (a live source may be a
                 generator that blocks until its next frame)
        outputs : subset of ``mesh``, ``mesh_detailed``, ``displacement``, ``albedo``,
                  ``normal_map``
        clamp : bool, optional        limit extrapolated detail (None: the server's default)
        max_in_flight : int           frames sent ahead and not yet answered, at most
        start_frame : int             the first frame's number (replies echo it in ``frame``)
        timeout : float, optional     seconds for the whole stream
        half : bool                   maps as float16 (half the bytes on the wire; each
                                      value within 2^-11 relative, 2^-25 absolute, of float32)

        Yields
        ------
        dict   see :func:`decode_reply`

        Raises
        ------
        NotFound, Unprocessable, Conflict, Unauthorized, Overloaded, TransportError
            the stream's status (see :func:`stream_error`); ``ValueError`` for a frame that
            is not (M,3)
        """
        plan = StreamPlan(model_id, tuple(outputs), clamp, start_frame, self.token, half)
        window = threading.Semaphore(_check_depth(max_in_flight))
        done = threading.Event()
        failure: list[BaseException] = []

        def requests() -> Iterator[pb.MarkerFrame]:   # run by gRPC's sending thread
            source = iter(frames)
            try:
                while True:
                    # a slot first, then the frame: a live source is not read ahead of it
                    while not window.acquire(timeout=0.05):
                        if done.is_set():
                            return
                    if done.is_set():
                        return
                    try:
                        markers = next(source)
                    except StopIteration:
                        return
                    yield plan.message(markers)
            except Exception as error:               # handed to the caller, not lost
                failure.append(error)
                raise

        call = self._stream(requests(), metadata=plan.metadata, timeout=timeout)
        try:
            for reply in call:
                window.release()
                yield decode_reply(reply)
        except grpc.RpcError as error:
            if failure:
                raise failure[0] from None
            raise stream_error(error) from error
        finally:
            done.set()
            call.cancel()
        if failure:
            raise failure[0]


class AsyncStreamingClient:
    """The asynchronous gRPC client (``grpc.aio``): :meth:`synthesize` is an async iterator.

    Parameters are those of :class:`StreamingClient`, with a ``grpc.aio.Channel``; ``frames``
    may be an async iterable too.

    Examples
    --------
    >>> async with AsyncStreamingClient("127.0.0.1:50051") as stream:      # doctest: +SKIP
    ...     async for out in stream.synthesize(model_id, frames):
    ...         print(out["frame"], out["latency_ms"])
    """

    def __init__(self, target: str | None = None, token: str | None = None, *,
                 channel: Any = None, credentials: grpc.ChannelCredentials | None = None,
                 max_message_bytes: int = MAX_MESSAGE_BYTES):
        self.target = target or os.environ.get("FACESYNTH_GRPC") or DEFAULT_TARGET
        self.token = token if token is not None else os.environ.get("FACESYNTH_TOKEN") or None
        self._own = channel is None
        if channel is None:
            options = channel_options(max_message_bytes)
            channel = (grpc.aio.secure_channel(self.target, credentials, options) if credentials
                       else grpc.aio.insecure_channel(self.target, options))
        self._channel = channel
        self._stream = _stream_method(channel)

    async def close(self) -> None:
        """Close the channel made by this client (an injected one stays open)."""
        if self._own:
            await self._channel.close()

    async def __aenter__(self) -> "AsyncStreamingClient":
        return self

    async def __aexit__(self, *exc: Any) -> None:
        await self.close()

    async def synthesize(self, model_id: str, frames: Iterable[Any] | AsyncIterable[Any],
                         outputs: Sequence[str] = DEFAULT_OUTPUTS, *,
                         clamp: bool | None = None, max_in_flight: int = DEFAULT_IN_FLIGHT,
                         start_frame: int = 0, timeout: float | None = None,
                         half: bool = False) -> AsyncIterator[dict[str, Any]]:
        """As :meth:`StreamingClient.synthesize`, as an async iterator."""
        plan = StreamPlan(model_id, tuple(outputs), clamp, start_frame, self.token, half)
        window = asyncio.Semaphore(_check_depth(max_in_flight))
        failure: list[BaseException] = []

        async def source() -> AsyncIterator[Any]:
            if hasattr(frames, "__aiter__"):
                async for markers in frames:       # type: ignore[union-attr]
                    yield markers
            else:
                for markers in frames:             # type: ignore[union-attr]
                    yield markers

        async def requests() -> AsyncIterator[pb.MarkerFrame]:
            frames_in = source()
            try:
                while True:
                    await window.acquire()       # a slot first, then the frame
                    try:
                        markers = await frames_in.__anext__()
                    except StopAsyncIteration:
                        return
                    yield plan.message(markers)
            except Exception as error:
                failure.append(error)
                raise

        call = self._stream(requests(), metadata=plan.metadata, timeout=timeout)
        try:
            async for reply in call:
                window.release()
                yield decode_reply(reply)
        except grpc.RpcError as error:
            if failure:
                raise failure[0] from None
            raise stream_error(error) from error
        finally:
            call.cancel()
        if failure:
            raise failure[0]
