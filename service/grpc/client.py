"""A small client of ``facesynth.v1.Synthesis/StreamSynthesize`` (tests and scripts; the SDK
comes separately).

>>> channel = grpc.insecure_channel("127.0.0.1:50051", options=channel_options())
>>> for out in stream_synthesize(channel, model_id, markers, outputs=("mesh", "displacement")):
...     out["vertices"], out["displacement"]          # (V,3), (H,W) float32
"""

from __future__ import annotations

from typing import Iterable, Iterator, Sequence

import grpc
import numpy as np

from service.grpc import codec
from service.grpc.facesynth.v1 import synthesis_pb2 as pb
from service.grpc.facesynth.v1 import synthesis_pb2_grpc as pb_grpc
from service.methods.outputs import STREAM_DEFAULT_OUTPUTS


def channel_options(max_message_bytes: int = codec.MAX_MESSAGE_BYTES) -> list[tuple[str, int]]:
    """Channel options that accept replies up to ``max_message_bytes`` (gRPC's default: 4 MiB)."""
    return [("grpc.max_receive_message_length", max_message_bytes),
            ("grpc.max_send_message_length", max_message_bytes)]


def _requests(model_id: str, frames: Iterable[np.ndarray], outputs: Sequence[str],
              clamp: bool | None, half: bool = False) -> Iterator[pb.MarkerFrame]:
    first = {"model_id": model_id, "outputs": list(outputs)}
    if clamp is not None:
        first["clamp"] = clamp
    if half:
        first["half"] = True
    for index, markers in enumerate(frames):
        yield codec.encode_markers(markers, index, **(first if index == 0 else {}))


def stream_synthesize(channel: grpc.Channel, model_id: str, frames_iter: Iterable[np.ndarray],
                      outputs: Sequence[str] = STREAM_DEFAULT_OUTPUTS, *, clamp: bool | None = None,
                      token: str | None = None, timeout: float | None = None,
                      half: bool = False) -> Iterator[dict[str, np.ndarray | int | float]]:
    """Stream marker frames to the server and yield its results, one per frame, in order.

    Parameters
    ----------
    channel : a gRPC channel to the server (see :func:`channel_options` for big maps)
    model_id : str
    frames_iter : iterable of (M,3) float markers, actor's unit, NaN for occluded; frames are
                  numbered 0, 1, … in the order given, and consumed as the stream needs them
                  (a live source can be a generator)
    outputs : subset of ``mesh``, ``mesh_detailed``, ``displacement``, ``albedo``, ``normal_map``
    clamp : limit extrapolated detail (None: the server's default, true)
    token : bearer token, for a server configured with tokens
    timeout : seconds for the whole stream (None: no deadline)
    half : maps as float16 (see ``synthesis.proto``, MarkerFrame.half)

    Yields
    ------
    dict as :func:`service.grpc.codec.decode_reply`: ``frame``, ``clamped``, ``latency_ms``,
    ``vertices`` (V,3) …, ``faces`` (T,3) int32 in the first result only. Arrays are read-only.

    Raises
    ------
    grpc.RpcError
        with the server's status (``.code()``, ``.details()``), e.g. NOT_FOUND, INVALID_ARGUMENT.
    """
    stub = pb_grpc.SynthesisStub(channel)
    metadata = [("authorization", f"Bearer {token}")] if token else None
    replies = stub.StreamSynthesize(_requests(model_id, frames_iter, outputs, clamp, half),
                                    metadata=metadata, timeout=timeout)
    for reply in replies:
        yield codec.decode_reply(reply)
