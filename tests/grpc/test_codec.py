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
