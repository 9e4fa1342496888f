"""NumPy arrays to and from the ``facesynth.v1`` messages (``facesynth/v1/synthesis.proto``).

One place for the wire layout that the server and the client share: markers as a repeated
float (M·3, NaN for occluded), meshes and maps as little-endian float32 / int32 ``bytes``.
Decoded arrays are zero-copy views of the message's bytes, hence read-only.
"""

from __future__ import annotations

from typing import Mapping, Sequence

import numpy as np

from service.grpc.facesynth.v1 import synthesis_pb2 as pb
from service.errors import InvalidInput
from service.io.half import to_float16
from service.methods import outputs as vocabulary
from service.methods.outputs import MAP_OUTPUTS, STREAM_DEFAULT_OUTPUTS

#: mesh outputs → their MeshFrame ``bytes`` field (and synthesize's result key)
MESH_FIELDS = {"mesh": "vertices", "mesh_detailed": "vertices_detailed"}
#: default gRPC message size limit, bytes, both directions: a reply with 1024² displacement,
#: albedo and normal maps is 28 MiB, plus the meshes
MAX_MESSAGE_BYTES = 64 * 2**20

F32 = np.dtype("<f4")
F16 = np.dtype("<f2")
I32 = np.dtype("<i4")


def check_outputs(outputs: Sequence[str]) -> tuple[str, ...]:
    """Validated outputs without repeats, in the given order;
    :data:`~service.methods.outputs.STREAM_DEFAULT_OUTPUTS` for none (MeshFrame fields and
    groups are named like the outputs; the map outputs are its ``Map`` fields)."""
    return vocabulary.check_outputs(outputs) or STREAM_DEFAULT_OUTPUTS


# ---------------------------------------------------------------------- MarkerFrame
def encode_markers(markers: np.ndarray, frame: int, **first: object) -> pb.MarkerFrame:
    """A MarkerFrame for markers (M,3), actor's unit, NaN for occluded.

    ``first`` takes the first message's fields (``model_id``, ``outputs``, ``clamp``).
    """
    markers = np.asarray(markers, dtype=np.float32)
    if markers.ndim != 2 or markers.shape[1] != 3:
        raise ValueError(f"markers must be (M,3), got {markers.shape}")
    return pb.MarkerFrame(frame=frame, markers=markers.ravel(), marker_count=len(markers), **first)


def decode_markers(msg: pb.MarkerFrame) -> np.ndarray:
    """Markers (M,3) float32 of a MarkerFrame; :class:`InvalidInput` for a bad length."""
    values = np.array(msg.markers, dtype=np.float32)
    count = msg.marker_count
    if count and len(values) != 3 * count:
        raise InvalidInput(f"{len(values)} marker values for marker_count {count}, expected {3 * count}")
    if len(values) % 3:
        raise InvalidInput(f"{len(values)} marker values is not a multiple of 3 (x, y, z per marker)")
    return values.reshape(-1, 3)


# ---------------------------------------------------------------------- MeshFrame
def encode_map(values: np.ndarray, half: bool = False) -> pb.Map:
    """A Map of a (H,W) or (H,W,C) array: float32, or with ``half`` binary16 (rounded to
    nearest: within 2^-11 relative, 2^-25 absolute, of float32; beyond 65504 is +-inf;
    :func:`service.io.half.to_float16`, NumPy's rounding bit for bit, vectorized)."""
    values = to_float16(values) if half else np.asarray(values, dtype=F32)
    H, W = values.shape[:2]
    return pb.Map(height=H, width=W, channels=1 if values.ndim == 2 else values.shape[2],
                  data=values.tobytes(), half=half)


def decode_map(m: pb.Map) -> np.ndarray:
    """(H,W) for one channel, else (H,W,C); float32, or float16 for a ``half`` map."""
    shape = (m.height, m.width) + ((m.channels,) if m.channels != 1 else ())
    return np.frombuffer(m.data, F16 if m.half else F32).reshape(shape)


def encode_reply(result: Mapping[str, np.ndarray], outputs: Sequence[str], frame: int,
                 faces: bool, index: int = 0, half: bool = False) -> pb.MeshFrame:
    """The MeshFrame of frame ``index`` of a ``synthesize`` result.

    Parameters
    ----------
    result : dict       ``synthesize``'s arrays: vertices (F,V,3), vertices_detailed (F,V,3),
                        faces (T,3), displacement (F,H,W), albedo / normal_map (F,H,W,3),
                        clamped (F,)
    outputs : names of :data:`~service.methods.outputs.OUTPUTS` to put in the reply (others in ``result`` are left out)
    frame : the client's frame number to echo;  faces : include the triangles
    half : the maps as binary16 (:func:`encode_map`)
    """
    reply = pb.MeshFrame(frame=frame, clamped=float(result["clamped"][index]))
    for output, key in MESH_FIELDS.items():
        if output in outputs:
            V = np.asarray(result[key][index], dtype=F32)
            reply.vertex_count = len(V)
            setattr(reply, key, V.tobytes())
    if faces:
        reply.faces = np.asarray(result["faces"], dtype=I32).tobytes()
    for key in MAP_OUTPUTS:
        if key in outputs:
            getattr(reply, key).CopyFrom(encode_map(result[key][index], half))
    return reply


def decode_reply(reply: pb.MeshFrame) -> dict[str, np.ndarray | int | float]:
    """The arrays of a MeshFrame, under ``synthesize``'s keys, for the fields it carries.

    Returns
    -------
    dict with ``frame`` int, ``clamped`` float, ``latency_ms`` float, and as present:
    ``vertices`` / ``vertices_detailed`` (V,3) float32, ``faces`` (T,3) int32,
    ``displacement`` (H,W), ``albedo`` / ``normal_map`` (H,W,3), float32 (float16 for
    half maps).
    """
    out: dict[str, np.ndarray | int | float] = {
        "frame": reply.frame, "clamped": reply.clamped, "latency_ms": reply.latency_ms}
    for key in MESH_FIELDS.values():
        data = getattr(reply, key)
        if data:
            out[key] = np.frombuffer(data, F32).reshape(reply.vertex_count, 3)
    if reply.faces:
        out["faces"] = np.frombuffer(reply.faces, I32).reshape(-1, 3)
    for key in MAP_OUTPUTS:
        if reply.HasField(key):
            out[key] = decode_map(getattr(reply, key))
    return out
