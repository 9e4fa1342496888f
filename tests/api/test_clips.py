"""Clips: NPZ and multipart (per-frame OBJ + marker file) uploads checked against the actor."""

from __future__ import annotations

import io

import numpy as np

from service.io.markers import MarkerSequence, write_markers_csv, write_markers_trc
from service.io.mesh import Mesh, write_obj
from tests.api.conftest import NPZ, assert_problem, grid, npz


def clip_body(frames=3, vertices=None, markers=None, **extra) -> bytes:
    V = grid()[0]
    vertices = np.stack([V + 0.1 * f for f in range(frames)]) if vertices is None else vertices
    markers = np.ones((frames, 3, 3)) if markers is None else markers
    return npz(vertices=vertices, markers=markers, **extra)


def post(client, actor_id, body, headers=NPZ, **params):
    return client.post(f"/v1/actors/{actor_id}/clips", content=body, headers=headers,
                       params=params)


def test_clip_npz_add_list_get_delete(client, grid_actor):
    response = post(client, grid_actor, clip_body(3, fps=np.float64(60),
                                                  albedo=np.zeros((3, 8, 8, 3), np.float32)),
                    name="smile")
    assert response.status_code == 201, response.text
    clip = response.json()
    assert clip["frames"] == 3 and clip["name"] == "smile" and clip["clip_id"].startswith("clp_")
    url = f"/v1/actors/{grid_actor}/clips"
    assert [c["clip_id"] for c in client.get(url).json()["items"]] == [clip["clip_id"]]
    assert clip.pop("notes") == []           # the upload's answer only: an NPZ has none
    assert client.get(f"{url}/{clip['clip_id']}").json() == clip
    assert client.delete(f"{url}/{clip['clip_id']}").status_code == 204
    assert_problem(client.get(f"{url}/{clip['clip_id']}"), 404)
    assert client.get(url).json()["items"] == []


def test_clip_rejects_vertex_count_mismatch(client, grid_actor):
    vertices = np.zeros((2, 35, 3))
    assert_problem(post(client, grid_actor, clip_body(2, vertices=vertices)), 422,
                   "35 vertices", "the neutral has 36")


def test_clip_rejects_wrong_marker_count(client, grid_actor):
    assert_problem(post(client, grid_actor, clip_body(2, markers=np.zeros((2, 4, 3)))), 422,
                   "4 markers per frame", "layout has 3")


def test_clip_rejects_frame_count_mismatch_and_nan(client, grid_actor):
    assert_problem(post(client, grid_actor, clip_body(2, markers=np.zeros((3, 3, 3)))), 422,
                   "'markers' has 3 frames", "'vertices' has 2")
    vertices = np.stack([grid()[0]] * 3)
    vertices[2, 5, 0] = np.nan
    assert_problem(post(client, grid_actor, clip_body(3, vertices=vertices)), 422,
                   "clip frame 2 vertex 5", "non-finite")
    markers = np.ones((3, 3, 3))
    markers[1, 2] = np.nan                            # occluded: fine
    assert post(client, grid_actor, clip_body(3, markers=markers)).status_code == 201
    markers[1, 0, 0] = np.inf
    assert_problem(post(client, grid_actor, clip_body(3, markers=markers)), 422,
                   "clip frame 1 marker 0")


def test_clip_rejects_non_square_maps(client, grid_actor):
    assert_problem(post(client, grid_actor, clip_body(2, displacement=np.zeros((2, 8, 16)))),
                   422, "'displacement'", "texels per side")


def test_clip_needs_neutral_and_markers(client, actor_id):
    assert_problem(post(client, actor_id, clip_body(2)), 409, "no neutral mesh")


def test_clip_of_unknown_actor_or_clip_is_404(client, grid_actor):
    assert_problem(post(client, "act_00000000000000000000000000", clip_body(1)), 404)
    assert_problem(client.delete(f"/v1/actors/{grid_actor}/clips/clp_00000000000000000000000000"),
                   404)


def test_clip_of_another_actor_is_404(client, grid_actor):
    clip_id = post(client, grid_actor, clip_body(1)).json()["clip_id"]
    other = client.post("/v1/actors", json={"name": "B"}).json()["id"]
    assert_problem(client.get(f"/v1/actors/{other}/clips/{clip_id}"), 404, "another actor")


def test_clip_wrong_content_type_is_415(client, grid_actor):
    assert_problem(post(client, grid_actor, clip_body(1), {"Content-Type": "application/json"}),
                   415, "application/x-npz", "multipart/form-data")


def _obj(vertices: np.ndarray) -> bytes:
    buffer = io.BytesIO()
    write_obj(buffer, Mesh(vertices, grid()[1]))
    return buffer.getvalue()


def _csv(frames: int, names=("M0", "M1", "M2")) -> bytes:
    buffer = io.BytesIO()
    positions = np.arange(frames * len(names) * 3, dtype=float).reshape(frames, len(names), 3)
    write_markers_csv(buffer, MarkerSequence(positions, names))
    return buffer.getvalue()


def test_clip_multipart_obj_frames_and_marker_file(client, grid_actor):
    V = grid()[0]
    files = [("frames", (f"f{k}.obj", _obj(V + k), "model/obj")) for k in range(3)]
    files.append(("markers", ("take.csv", _csv(3, ("M2", "M0", "M1", "extra")), "text/csv")))
    response = client.post(f"/v1/actors/{grid_actor}/clips", files=files, data={"fps": "24"})
    assert response.status_code == 201, response.text
    assert response.json()["frames"] == 3


def test_clip_multipart_names_the_frame_with_the_wrong_vertex_count(client, grid_actor):
    V = grid()[0]
    files = [("frames", ("a.obj", _obj(V), "model/obj")),
             ("frames", ("b.obj", b"v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n", "model/obj")),
             ("markers", ("take.csv", _csv(2), "text/csv"))]
    assert_problem(client.post(f"/v1/actors/{grid_actor}/clips", files=files), 422,
                   "clip frame 1 ('b.obj') has 3 vertices, the neutral has 36")


def test_clip_multipart_marker_file_must_cover_the_layout(client, grid_actor):
    files = [("frames", ("a.obj", _obj(grid()[0]), "model/obj")),
             ("markers", ("take.csv", _csv(1, ("M0", "M1")), "text/csv"))]
    assert_problem(client.post(f"/v1/actors/{grid_actor}/clips", files=files), 422,
                   "lacks 1 of the layout's 3 markers: M2")
    files = [("frames", ("a.obj", _obj(grid()[0]), "model/obj"))]
    assert_problem(client.post(f"/v1/actors/{grid_actor}/clips", files=files), 422, "'markers'")


def test_clip_multipart_reports_the_marker_readers_notes(client, grid_actor):
    """A TRC whose NumFrames (5) disagrees with its 3 rows is read, and the answer says so."""
    buffer = io.BytesIO()
    positions = np.arange(3 * 3 * 3, dtype=float).reshape(3, 3, 3)
    write_markers_trc(buffer, MarkerSequence(positions, ("M0", "M1", "M2")), fps=30.0)
    lines = buffer.getvalue().decode().split("\n")
    values = lines[2].split("\t")
    assert (lines[1].split("\t")[2], values[2]) == ("NumFrames", "3")
    lines[2] = "\t".join(values[:2] + ["5"] + values[3:])
    V = grid()[0]
    files = [("frames", (f"f{k}.obj", _obj(V + k), "model/obj")) for k in range(3)]
    files.append(("markers", ("take.trc", "\n".join(lines).encode(), "text/plain")))
    response = client.post(f"/v1/actors/{grid_actor}/clips", files=files)
    assert response.status_code == 201, response.text
    assert response.json()["frames"] == 3
    assert response.json()["notes"] == [
        "the TRC header says NumFrames 5 but the file has 3 frame rows; the 3 rows were read"]
    # the CSV of the other multipart test reads as declared: no notes
    files[-1] = ("markers", ("take.csv", _csv(3), "text/csv"))
    assert client.post(f"/v1/actors/{grid_actor}/clips", files=files).json()["notes"] == []


def test_a_clip_name_with_a_nul_is_refused_before_anything_is_stored(client, grid_actor):
    """issue 16, defects 1 and 7: ``?name=a%00b`` used to reach PostgreSQL and fail there."""
    actor_id = grid_actor
    response = client.post(f"/v1/actors/{actor_id}/clips?name=a%00b", content=b"x", headers=NPZ)
    assert_problem(response, 422, "NUL")
    assert client.get(f"/v1/actors/{actor_id}/clips").json()["items"] == []
