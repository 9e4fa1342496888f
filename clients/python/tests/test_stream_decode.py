"""The streaming clients' reply decoding: a MeshFrame's bytes read field by field give what
the parsed message gives, as views of the bytes."""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("grpc")

from facesynth_client._proto.facesynth.v1 import synthesis_pb2 as pb  # noqa: E402
from facesynth_client.streaming import decode_reply  # noqa: E402


def _frame(half: bool, **fields) -> pb.MeshFrame:
    rng = np.random.default_rng(5)
    V = rng.normal(size=(4, 3)).astype(np.float32)
    disp = rng.normal(size=(3, 2)).astype(np.float16 if half else np.float32)
    rgb = rng.normal(size=(3, 2, 3)).astype(np.float16 if half else np.float32)
    msg = pb.MeshFrame(frame=301, vertex_count=4, vertices=V.tobytes(),
                       vertices_detailed=(V + 1).tobytes(),
                       faces=np.array([[0, 1, 2], [1, 2, 3]], "<i4").tobytes(),
                       displacement=pb.Map(height=3, width=2, channels=1, data=disp.tobytes(), half=half),
                       normal_map=pb.Map(height=3, width=2, channels=3, data=rgb.tobytes(), half=half),
                       clamped=0.125, latency_ms=17.25)
    for name, value in fields.items():
        if isinstance(value, pb.Map):
            getattr(msg, name).CopyFrom(value)
        else:
            setattr(msg, name, value)
    return msg


def _same(a: dict, b: dict) -> None:
    assert a.keys() == b.keys()
    for key in a:
        if isinstance(a[key], np.ndarray):
            assert a[key].dtype == b[key].dtype and a[key].shape == b[key].shape, key
            np.testing.assert_array_equal(a[key], b[key])
        else:
            assert type(a[key]) is type(b[key]) and a[key] == b[key], key


@pytest.mark.parametrize("half", [False, True])
@pytest.mark.parametrize("fields", [{}, {"frame": 0, "clamped": 0.0, "faces": b""},
                                    {"clamped": -0.0, "vertices_detailed": b""},
                                    {"albedo": pb.Map()},             # present, every field default
                                    {"vertex_count": 0, "vertices": b"", "vertices_detailed": b""}])
def test_the_bytes_decode_as_the_message(half, fields):
    msg = _frame(half, **fields)
    data = msg.SerializeToString()
    got = decode_reply(data)
    _same(got, decode_reply(msg))
    assert not got["vertices" if "vertices" in got else "displacement"].flags.writeable
    if "vertices" in got:                                  # a view of the received bytes
        assert np.shares_memory(got["vertices"], np.frombuffer(data, np.uint8))


def test_unknown_fields_are_skipped_and_a_repeated_field_is_the_parsers():
    msg = _frame(False)
    data = msg.SerializeToString()
    unknown = bytes([0x60 | 0, 0x96, 0x01]) + bytes([0x6A, 3]) + b"abc"   # field 12 varint, 13 bytes
    _same(decode_reply(unknown + data), decode_reply(msg))
    # field 1 twice: protobuf keeps the last; a Map sent twice is merged — left to the parser
    again = data + pb.MeshFrame(frame=7, displacement=pb.Map(height=3)).SerializeToString()
    got = decode_reply(again)
    _same(got, decode_reply(pb.MeshFrame.FromString(again)))
    assert got["frame"] == 7 and got["displacement"].shape == (3, 2)


def test_a_truncated_reply_is_the_parsers_error():
    from google.protobuf.message import DecodeError

    data = _frame(True).SerializeToString()
    for cut in (1, 2, len(data) // 2, len(data) - 1):
        with pytest.raises(DecodeError):
            decode_reply(data[:cut])
