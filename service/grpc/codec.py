"""NumPy arrays to and from the ``facesynth.v1`` messages (``facesynth/v1/synthesis.proto``).

One place for the wire layout that the server and the client share: markers as a repeated
float (M·3, NaN for occluded), meshes and maps as little-endian float32 / int32 ``bytes``.
Decoded arrays are zero-copy views of the message's bytes, hence read-only.

The server sends its replies as the MeshFrame's protobuf encoding written directly
(:func:`reply_pieces`, :func:`join_reply`; the binary wire format of
https://protobuf.dev/programming-guides/encoding/), the same bytes as
``encode_reply(...).SerializeToString()``: building the message object copies each array
three times on the way (``tobytes``, the field assignment, the serialization) — a level-1
maps frame's 8.5 MiB (half) or 16.5 MiB (float32) — where the direct form copies it once,
from the result arrays into the bytes handed to gRPC.
"""

from __future__ import annotations

from typing import Mapping, Sequence

import numpy as np

from service.grpc.facesynth.v1 import synthesis_pb2 as pb
from service.errors import InvalidInput
from service.geometry.ranges import scratch
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

    The message form of a reply: the server sends :func:`reply_pieces` instead (same bytes,
    one copy less per array), and this is the definition those bytes are tested against.

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


# ---------------------------------------------------------------------- MeshFrame, wire form
#: protobuf wire types (https://protobuf.dev/programming-guides/encoding/)
VARINT, I64, LEN, I32_WIRE = 0, 1, 2, 5
#: MeshFrame's and Map's field numbers by name, from the generated descriptors
MESH_FRAME_NUMBERS = {f.name: f.number for f in pb.MeshFrame.DESCRIPTOR.fields}
MAP_NUMBERS = {f.name: f.number for f in pb.Map.DESCRIPTOR.fields}
F64 = np.dtype("<f8")


def varint(value: int) -> bytes:
    """The base-128 varint of a non-negative int (7 bits a byte, low first)."""
    out = bytearray()
    while value >= 0x80:
        out.append((value & 0x7F) | 0x80)
        value >>= 7
    out.append(value)
    return bytes(out)


def tag(field: int, wire_type: int) -> bytes:
    """A field's key: ``varint(field << 3 | wire_type)``."""
    return varint(field << 3 | wire_type)


def _scalar(field: int, value: int) -> bytes:
    """A uint32 / bool field; proto3 leaves out a zero."""
    return tag(field, VARINT) + varint(int(value)) if value else b""


def _fixed(field: int, value: float, dtype: np.dtype) -> bytes:
    """A float (``<f4``) or double (``<f8``) field; proto3 leaves out +0.0 (all bits zero)."""
    data = np.asarray(value, dtype).tobytes()
    return tag(field, I32_WIRE if dtype.itemsize == 4 else I64) + data if any(data) else b""


def _payload(values: np.ndarray, dtype: np.dtype) -> memoryview:
    """The bytes of ``values`` as ``dtype``, C order: a view of the array when it already is."""
    return memoryview(np.ascontiguousarray(values, dtype=dtype)).cast("B")


def _length_delimited(field: int, pieces: list) -> list:
    """A bytes or message field around ``pieces`` (its payload); none when they are empty."""
    size = sum(len(p) for p in pieces)
    return [tag(field, LEN) + varint(size), *pieces] if size else []


def map_pieces(field: int, values: np.ndarray, half: bool = False) -> list:
    """The pieces of a Map field of a (H,W) or (H,W,C) array, as :func:`encode_map`'s message.
    Half maps are converted into the calling thread's work array (``scratch``), valid until
    its next call: join the pieces before then; a float16 array (a map the model wrote in
    half precision) is sent as it is."""
    H, W = values.shape[:2]
    if half and values.dtype == np.float16:
        data = _payload(values, F16)
    elif half:
        data = to_float16(values, out=scratch(f"grpc.half.{field}", (values.size,), np.float16))
        data = memoryview(data).cast("B")
    else:
        data = _payload(values, F32)
    head = (_scalar(MAP_NUMBERS["height"], H) + _scalar(MAP_NUMBERS["width"], W)
            + _scalar(MAP_NUMBERS["channels"], 1 if values.ndim == 2 else values.shape[2]))
    body = [head, *_length_delimited(MAP_NUMBERS["data"], [data]), _scalar(MAP_NUMBERS["half"], half)]
    size = sum(len(p) for p in body)
    return [tag(field, LEN) + varint(size), *body]      # a set message field is sent even if empty


def reply_pieces(result: Mapping[str, np.ndarray], outputs: Sequence[str], frame: int,
                 faces: bool, index: int = 0, half: bool = False) -> list:
    """The MeshFrame of :func:`encode_reply` (same parameters) in its wire encoding, as a
    list of bytes and zero-copy views of ``result``'s arrays, all but ``latency_ms`` (the
    last field): :func:`join_reply` adds it and makes the message's bytes."""
    f = MESH_FRAME_NUMBERS               # fields in number order, as protobuf serializes them
    meshes = {key: result[key][index] for output, key in MESH_FIELDS.items() if output in outputs}
    pieces = [_scalar(f["frame"], frame),
              _scalar(f["vertex_count"], len(next(iter(meshes.values()))) if meshes else 0)]
    for key in sorted(meshes, key=f.get):
        pieces += _length_delimited(f[key], [_payload(meshes[key], F32)])
    if faces:
        pieces += _length_delimited(f["faces"], [_payload(result["faces"], I32)])
    for key in sorted((k for k in MAP_OUTPUTS if k in outputs), key=f.get):
        pieces += map_pieces(f[key], result[key][index], half)
    pieces.append(_fixed(f["clamped"], result["clamped"][index], F32))
    return pieces


def join_reply(pieces: list, latency_ms: float) -> bytes:
    """The serialized MeshFrame of :func:`reply_pieces` with ``latency_ms`` (one copy of
    every piece): bit for bit ``encode_reply(...)`` with that ``latency_ms`` serialized."""
    return b"".join([*pieces, _fixed(MESH_FRAME_NUMBERS["latency_ms"], latency_ms, F64)])


def serialize_reply(reply: pb.MeshFrame | bytes) -> bytes:
    """A reply's bytes for gRPC: a MeshFrame serialized, a wire-form reply (bytes) as is."""
    return reply if isinstance(reply, bytes) else reply.SerializeToString()
