"""Arrays to and from the facesynth.v1 messages: layout, byte order, validation."""

from __future__ import annotations

import numpy as np
import pytest

from service.grpc import codec
from service.methods.inputs import InvalidInput


def test_maps_round_trip_as_little_endian_row_major_float32():
    disp = np.arange(6, dtype=np.float64).reshape(2, 3)
    m = codec.encode_map(disp)
    assert (m.height, m.width, m.channels) == (2, 3, 1)
    assert m.data == np.arange(6, dtype="<f4").tobytes()
    np.testing.assert_array_equal(codec.decode_map(m), disp)
    rgb = np.random.default_rng(0).random((4, 5, 3)).astype(np.float32)
    assert codec.decode_map(codec.encode_map(rgb)).shape == (4, 5, 3)
    np.testing.assert_array_equal(codec.decode_map(codec.encode_map(rgb)), rgb)


def test_markers_keep_nan_and_check_their_count():
    markers = np.array([[1.5, 2, 3], [np.nan, np.nan, np.nan]])
    msg = codec.encode_markers(markers, frame=7, model_id="m")
    assert (msg.frame, msg.marker_count, msg.model_id) == (7, 2, "m")
    np.testing.assert_array_equal(codec.decode_markers(msg), markers.astype(np.float32))
    del msg.markers[-1]
    with pytest.raises(InvalidInput, match="5 marker values for marker_count 2, expected 6"):
        codec.decode_markers(msg)
    msg.marker_count = 0
    with pytest.raises(InvalidInput, match="not a multiple of 3"):
        codec.decode_markers(msg)


def test_outputs_default_to_mesh_drop_repeats_and_reject_unknown_names():
    assert codec.check_outputs([]) == ("mesh",)
    assert codec.check_outputs(["normal_map", "mesh", "normal_map"]) == ("normal_map", "mesh")
    with pytest.raises(InvalidInput, match=r"unknown outputs \['pores'\]"):
        codec.check_outputs(["mesh", "pores"])


def test_a_reply_carries_only_the_asked_outputs_and_faces_on_request():
    result = {"vertices": np.ones((2, 4, 3)), "vertices_detailed": np.zeros((2, 4, 3)),
              "faces": np.array([[0, 1, 2], [0, 2, 3]]), "displacement": np.ones((2, 3, 3)),
              "clamped": np.array([0.0, 0.25])}
    reply = codec.encode_reply(result, ("mesh", "displacement"), frame=9, faces=False, index=1)
    assert reply.vertex_count == 4 and not reply.vertices_detailed and not reply.faces
    out = codec.decode_reply(reply)
    assert set(out) == {"frame", "clamped", "latency_ms", "vertices", "displacement"}
    assert out["frame"] == 9 and out["clamped"] == 0.25 and out["displacement"].shape == (3, 3)
    first = codec.decode_reply(codec.encode_reply(result, ("mesh_detailed",), 0, faces=True))
    assert first["faces"].dtype == np.int32 and first["faces"].tolist() == [[0, 1, 2], [0, 2, 3]]
    assert "vertices" not in first and first["vertices_detailed"].shape == (4, 3)


def test_half_maps_round_trip_as_float16():
    rgb = np.linspace(-2, 2, 60, dtype=np.float32).reshape(4, 5, 3)
    m = codec.encode_map(rgb, half=True)
    assert m.half and len(m.data) == rgb.size * 2
    out = codec.decode_map(m)
    assert out.dtype == np.float16
    np.testing.assert_array_equal(out, rgb.astype(np.float16))
    assert not codec.encode_map(rgb).half


@pytest.mark.parametrize("outputs", [("mesh",), ("mesh", "displacement", "normal_map"),
                                     ("mesh_detailed", "albedo"), ("displacement",),
                                     ("mesh", "mesh_detailed", "displacement", "albedo",
                                      "normal_map")])
@pytest.mark.parametrize("half", [False, True])
@pytest.mark.parametrize("frame, faces, index", [(0, True, 0), (7, False, 1), (300, True, 1)])
def test_the_wire_form_is_the_messages_serialization_bit_for_bit(outputs, half, frame, faces, index):
    """join_reply(reply_pieces(...)) == encode_reply(...) serialized, with latency_ms (and with
    half, for maps already float16 as the model writes them); also
    for clamped 0 and frame 0 (left out by proto3), -0.0 (sent), a float64 mesh (converted)
    and maps with values beyond float16's range."""
    rng = np.random.default_rng(3)
    result = {"vertices": rng.normal(size=(2, 5, 3)).astype(np.float32),
              "vertices_detailed": rng.normal(size=(2, 5, 3)),          # float64: converted
              "faces": np.array([[0, 1, 2], [2, 3, 4]], np.int64),
              "displacement": rng.normal(size=(2, 6, 4)).astype(np.float32) * 1e5,
              "albedo": rng.random((2, 3, 3, 3)).astype(np.float32),
              "normal_map": rng.normal(size=(2, 6, 4, 3)).astype(np.float32),
              "clamped": np.array([0.0, -0.0 if frame == 7 else 0.3])}
    for latency in (0.0, 12.345):
        wire = codec.join_reply(codec.reply_pieces(result, outputs, frame, faces, index, half), latency)
        message = codec.encode_reply(result, outputs, frame, faces, index, half)
        message.latency_ms = latency
        assert wire == message.SerializeToString()
        assert codec.serialize_reply(wire) is wire
        assert codec.serialize_reply(message) == wire
        if half:                  # maps the model wrote as float16 (synthesize(half=True)): sent as they are
            with np.errstate(over="ignore"):
                written = {k: v.astype(np.float16) if k in ("displacement", "albedo", "normal_map") else v
                           for k, v in result.items()}
            assert codec.join_reply(codec.reply_pieces(written, outputs, frame, faces, index, half), latency) == wire


def test_varints_and_keys_by_hand():
    assert codec.varint(0) == b"\x00" and codec.varint(1) == b"\x01" and codec.varint(127) == b"\x7f"
    assert codec.varint(128) == b"\x80\x01" and codec.varint(300) == b"\xac\x02"
    assert codec.varint(2**32 - 1) == b"\xff\xff\xff\xff\x0f"
    assert codec.tag(1, codec.VARINT) == b"\x08" and codec.tag(10, codec.I64) == b"\x51"
    assert codec.tag(9, codec.I32_WIRE) == b"\x4d" and codec.tag(8, codec.LEN) == b"\x42"
