"""Actors, the neutral upload and the marker layout, with every refusal."""

from __future__ import annotations

import numpy as np
import pytest

from tests.api.conftest import NPZ, assert_problem, grid, layout_body, npz

JSON = {"Content-Type": "application/json"}


def put_neutral(client, actor_id, body, headers=NPZ):
    return client.put(f"/v1/actors/{actor_id}/neutral", content=body, headers=headers)


def test_actor_create_get_list_delete(client):
    created = client.post("/v1/actors", json={"name": "Ada", "metadata": {"rig": "ict"}})
    assert created.status_code == 201
    actor = created.json()
    assert created.headers["location"] == f"/v1/actors/{actor['id']}"
    assert actor["name"] == "Ada" and actor["metadata"] == {"rig": "ict"}
    assert actor["vertex_count"] is None and actor["marker_count"] is None
    assert client.get(f"/v1/actors/{actor['id']}").json() == actor
    assert [a["id"] for a in client.get("/v1/actors").json()["items"]] == [actor["id"]]
    assert client.delete(f"/v1/actors/{actor['id']}").status_code == 204
    assert_problem(client.get(f"/v1/actors/{actor['id']}"), 404, actor["id"])


def test_create_actor_rejects_bad_bodies(client):
    body = assert_problem(client.post("/v1/actors", json={"name": ""}), 422, "name")
    assert body["errors"][0]["loc"] == ["body", "name"]
    assert_problem(client.post("/v1/actors", json={"name": "A", "nmae": 1}), 422, "nmae")
    assert_problem(client.post("/v1/actors", content=b'{"name": "A"', headers=JSON), 400,
                   "not valid JSON")
    assert_problem(client.post("/v1/actors", content=b"name=A",
                               headers={"Content-Type": "application/x-www-form-urlencoded"}),
                   415, "application/json")


def test_unknown_and_malformed_ids_are_404(client):
    assert_problem(client.get("/v1/actors/act_00000000000000000000000000"), 404, "not found")
    assert_problem(client.get("/v1/actors/..%2F..%2Fetc%2Fpasswd"), 404)
    assert_problem(client.get("/v1/actors/../../etc/passwd"), 404)
    assert_problem(client.delete("/v1/actors/ACT_X"), 404)


def test_put_neutral_npz_reports_counts_and_seams(client, actor_id):
    V, F, uv = grid()
    uv_faces = F.copy()
    uv2 = np.concatenate([uv, uv[:1] + 0.01])           # vertex 0 gets a second uv: a seam
    uv_faces[np.flatnonzero((F == 0).any(axis=1))[0], 0] = len(uv)
    response = put_neutral(client, actor_id, npz(vertices=V, faces=F, uv=uv2, uv_faces=uv_faces,
                                                 region_face=np.ones(len(V), bool)))
    assert response.status_code == 200, response.text
    assert response.json() == {"vertex_count": 36, "triangle_count": 50, "uv_seams": 1,
                               "polygons_split": 0, "regions": ["face"]}
    actor = client.get(f"/v1/actors/{actor_id}").json()
    assert (actor["vertex_count"], actor["triangle_count"]) == (36, 50)


def test_put_neutral_obj_keeps_order_and_reports_the_quad_split(client, actor_id):
    obj = ("v 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nv 2 0 0\nv 2 1 0\n"
           "vt 0 0\nvt 0.5 0\nvt 0.5 1\nvt 0 1\nvt 1 0\nvt 1 1\n"
           "f 1/1 2/2 3/3 4/4\nf 2/2 5/5 6/6\nf 2/2 6/6 3/3\n")
    response = put_neutral(client, actor_id, obj.encode(), {"Content-Type": "model/obj"})
    assert response.status_code == 200, response.text
    assert response.json()["triangle_count"] == 4 and response.json()["polygons_split"] == 1


def test_put_neutral_rejects_nan(client, actor_id):
    V, F, uv = grid()
    V[7, 1] = np.nan
    assert_problem(put_neutral(client, actor_id, npz(vertices=V, faces=F, uv=uv)), 422,
                   "vertex 7", "non-finite")


def test_put_neutral_rejects_face_index_out_of_range(client, actor_id):
    V, F, uv = grid()
    F[3, 2] = 99
    assert_problem(put_neutral(client, actor_id, npz(vertices=V, faces=F, uv=uv)), 422,
                   "face 3", "vertex 99", "36 vertices")


def test_put_neutral_rejects_degenerate_triangles(client, actor_id):
    V, F, uv = grid()
    V[F[5, 2]] = (V[F[5, 0]] + V[F[5, 1]]) / 2       # a collinear (zero-area) triangle ...
    F[9] = [F[9, 0], F[9, 0], F[9, 1]]                # ... and one with a repeated corner
    body = assert_problem(put_neutral(client, actor_id, npz(vertices=V, faces=F, uv=uv)), 422,
                          "degenerate triangle", "first is triangle")
    assert "zero area" in body["detail"]


def test_put_neutral_rejects_non_manifold_edges(client, actor_id):
    V, F, uv = grid()
    V = np.concatenate([V, [[5.0, 5.0, 9.0]]])
    uv = np.concatenate([uv, [[0.5, 0.5]]])
    a, b = F[0, 0], F[0, 2]                           # the cell diagonal: two triangles
    F = np.concatenate([F, [[a, b, len(V) - 1]]])     # a third one on edge (a, b)
    assert_problem(put_neutral(client, actor_id, npz(vertices=V, faces=F, uv=uv)), 422,
                   "1 non-manifold edge", f"edge ({min(a, b)}, {max(a, b)})")


def test_put_neutral_rejects_missing_or_out_of_tile_uv(client, actor_id):
    V, F, uv = grid()
    assert_problem(put_neutral(client, actor_id, npz(vertices=V, faces=F)), 422, "no UV layout")
    assert_problem(put_neutral(client, actor_id, npz(vertices=V, faces=F, uv=uv + 1)), 422,
                   "outside the unit tile")


def test_put_neutral_obj_with_faces_lacking_uvs_says_how_many_and_why(client, actor_id):
    """Two objects, one with v/vt corners and one with v//vn (it reads: NO_UV rows); the
    neutral is refused naming the 3 untextured triangles of 4, not an index -1."""
    obj = ("v 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nv 2 0 0\nv 2 1 0\n"
           "vt 0 0\nvt 0.5 0\nvt 0.5 1\nvn 0 0 1\n"
           "o textured\nf 1/1 2/2 3/3\n"
           "o bare\nf 1//1 3//1 4//1\nf 2//1 5//1 6//1\nf 2//1 6//1 3//1\n")
    body = assert_problem(put_neutral(client, actor_id, obj.encode(),
                                      {"Content-Type": "model/obj"}), 422,
                          "3 of the neutral's 4 triangles have no UVs", "first is triangle 1",
                          "every triangle of a neutral needs UVs")
    assert "-1" not in body["detail"] and "out of range" not in body["detail"]
    # the same mesh as an NPZ with NO_UV rows: the same answer
    V = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [2, 0, 0], [2, 1, 0]], float)
    F = np.array([[0, 1, 2], [0, 2, 3], [1, 4, 5], [1, 5, 2]])
    uv_faces = np.array([[0, 1, 2], [-1, -1, -1], [-1, -1, -1], [0, 1, 2]])
    assert_problem(put_neutral(client, actor_id, npz(vertices=V, faces=F, uv=V[:3, :2] / 2,
                                                     uv_faces=uv_faces)), 422,
                   "2 of the neutral's 4 triangles have no UVs", "first is triangle 1")


def test_put_neutral_rejects_bad_archives(client, actor_id):
    V, F, uv = grid()
    assert_problem(put_neutral(client, actor_id, npz(vertices=V, faces=F, uv=uv, colour=V)),
                   422, "unexpected array 'colour'")
    assert_problem(put_neutral(client, actor_id, npz(vertices=V, uv=uv)), 422, "lacks 'faces'")
    assert_problem(put_neutral(client, actor_id, npz(vertices=V[:, :2], faces=F)), 422,
                   "'vertices' has shape (36, 2)")
    pickled = npz(vertices=np.array([object()] * 3, dtype=object), faces=F)
    assert_problem(put_neutral(client, actor_id, pickled), 422, "Python objects")
    assert_problem(put_neutral(client, actor_id, b"not a zip"), 422, "not a readable .npz")
    assert_problem(put_neutral(client, actor_id, b"", NPZ), 400, "empty")


def test_put_neutral_rejects_wrong_content_type(client, actor_id):
    V, F, uv = grid()
    assert_problem(put_neutral(client, actor_id, npz(vertices=V, faces=F, uv=uv),
                               {"Content-Type": "application/octet-stream"}), 415,
                   "application/octet-stream", "application/x-npz", "model/obj")


def test_put_neutral_over_the_vertex_limit_is_413(client, actor_id, settings):
    V = np.zeros((settings.max_vertices + 1, 3))
    assert_problem(put_neutral(client, actor_id, npz(vertices=V, faces=np.zeros((1, 3), int))),
                   413, f"limit of {settings.max_vertices}")


def test_put_neutral_unknown_actor_is_404(client):
    V, F, uv = grid()
    assert_problem(put_neutral(client, "act_00000000000000000000000000",
                               npz(vertices=V, faces=F, uv=uv)), 404)


def test_put_markers_resolves_vertex_triangle_and_position(client, actor_id):
    V, F, uv = grid()
    put_neutral(client, actor_id, npz(vertices=V, faces=F, uv=uv))
    body = {"markers": [{"name": "A", "vertex": 8},
                        {"name": "B", "triangle": 3, "barycentric": [0.2, 0.3, 0.5]},
                        {"name": "C", "position": (V[14] + [0, 0, 0.5]).tolist()}]}
    response = client.put(f"/v1/actors/{actor_id}/markers", json=body)
    assert response.status_code == 200, response.text
    info = response.json()
    assert info["marker_count"] == 3 and info["snapped"] == 1
    assert 0 < info["max_snap_distance"] <= 0.5 + 1e-9
    assert client.get(f"/v1/actors/{actor_id}").json()["marker_count"] == 3


def test_put_markers_needs_the_neutral_first(client, actor_id):
    assert_problem(client.put(f"/v1/actors/{actor_id}/markers", content=layout_body(),
                              headers=JSON), 409, "no neutral mesh")


def test_put_markers_rejects_bad_layouts(client, actor_id):
    V, F, uv = grid()
    put_neutral(client, actor_id, npz(vertices=V, faces=F, uv=uv))
    url = f"/v1/actors/{actor_id}/markers"
    assert_problem(client.put(url, content=layout_body((0, 36)), headers=JSON), 422,
                   "vertex 36", "36 vertices")
    assert_problem(client.put(url, json={"markers": [{"name": "A", "triangle": 1,
                                                      "barycentric": [0.5, 0.6, 0.1]}]}),
                   422, "sum to 1")
    assert_problem(client.put(url, json={"markers": [{"name": "A", "vertex": 1},
                                                     {"name": "A", "vertex": 2}]}), 422,
                   "more than once")
    assert_problem(client.put(url, content=b"{", headers=JSON), 400, "not valid JSON")
    assert_problem(client.put(url, content=layout_body(), headers={"Content-Type": "text/plain"}),
                   415)


def test_replacing_the_neutral_keeps_its_topology_once_markers_exist(client, grid_actor):
    V, F, uv = grid()
    assert put_neutral(client, grid_actor, npz(vertices=V + 1, faces=F, uv=uv)).status_code == 200
    V2, F2, uv2 = grid(7)
    assert_problem(put_neutral(client, grid_actor, npz(vertices=V2, faces=F2, uv=uv2)), 409,
                   "marker layout", "36 vertices")


def test_delete_actor_with_models_needs_cascade(client, grid_actor, submitted):
    clip = npz(vertices=np.stack([grid()[0]] * 2), markers=np.zeros((2, 3, 3)))
    clip_id = client.post(f"/v1/actors/{grid_actor}/clips", content=clip,
                          headers=NPZ).json()["clip_id"]
    model = client.post(f"/v1/actors/{grid_actor}/models",
                        json={"kind": "pdm", "clips": [clip_id]}).json()
    assert_problem(client.delete(f"/v1/actors/{grid_actor}"), 409, "model", "cascade")
    assert client.delete(f"/v1/actors/{grid_actor}", params={"cascade": "true"}).status_code == 204
    assert_problem(client.get(f"/v1/models/{model['model_id']}"), 404)
    assert client.get(f"/v1/jobs/{model['job_id']}").json()["status"] == "cancelled"


def test_actor_metadata_is_bounded(client):
    assert_problem(client.post("/v1/actors", json={"name": "A", "metadata": {"x": "y" * 70000}}),
                   422, "metadata")


# -- poison strings never reach the database (issue 16, defect 1) ----------------------------
@pytest.mark.parametrize("body", [
    '{"name": "p", "metadata": {"k": "\\udfff"}}',             # a lone surrogate as a value
    '{"name": "p", "metadata": {"\\ud800": 1}}',               # ... as a key
    '{"name": "p", "metadata": {"a": [{"b": "x\\udc00y"}]}}',  # ... nested
    '{"name": "p\\udfff"}',                                    # ... in the name
    '{"name": "p", "metadata": {"k": "a\\u0000b"}}',           # a NUL character
])
def test_unencodable_strings_are_refused_before_anything_is_written(client, body):
    response = client.post("/v1/actors", content=body.encode(),
                           headers={"Content-Type": "application/json"})
    assert response.status_code == 422, response.text
    assert client.get("/v1/actors").status_code == 200
    assert client.get("/v1/actors").json()["items"] == []


# -- barycentrics written with 6 decimals (issue 16, defect 14) ------------------------------
def _triangle_layout(barycentrics) -> bytes:
    import json

    return json.dumps({"markers": [{"name": f"M{k}", "triangle": k, "barycentric": list(b)}
                                   for k, b in enumerate(barycentrics)]}).encode()


def test_barycentrics_off_by_rounding_are_renormalized_and_reported(client, actor_id):
    V, F, uv = grid()
    assert client.put(f"/v1/actors/{actor_id}/neutral", content=npz(vertices=V, faces=F, uv=uv),
                      headers=NPZ).status_code == 200
    exported = [(0.2, 0.3, 0.499999), (0.333333, 0.333333, 0.333333), (0.5, 0.5, 0.0),
                (1.00005, 0.0, 0.0), (-0.000001, 0.5, 0.500001)]
    response = client.put(f"/v1/actors/{actor_id}/markers", content=_triangle_layout(exported),
                          headers={"Content-Type": "application/json"})
    assert response.status_code == 200, response.text
    info = response.json()
    assert (info["marker_count"], info["renormalized"]) == (5, 4)   # (0.5, 0.5, 0) was exact
    off = [(0.2, 0.3, 0.4998)]                                       # 2e-4: a real error
    assert_problem(client.put(f"/v1/actors/{actor_id}/markers", content=_triangle_layout(off),
                              headers={"Content-Type": "application/json"}), 422, "M0")


def test_a_text_plain_neutral_is_415_not_422(client, actor_id):
    """issue 16, defect 9: text/plain was parsed as OBJ and answered 422."""
    assert_problem(client.put(f"/v1/actors/{actor_id}/neutral", content=b"v 0 0 0\n",
                              headers={"Content-Type": "text/plain"}), 415, "model/obj")


def test_an_int8_neutral_is_refused_and_does_not_replace_the_stored_one(client, grid_actor):
    """issue 16, defect 9: int8 vertices were accepted and replaced the actor's neutral."""
    V, F, uv = grid()
    before = client.get(f"/v1/actors/{grid_actor}").json()
    response = client.put(f"/v1/actors/{grid_actor}/neutral",
                          content=npz(vertices=V.astype(np.int8), faces=F, uv=uv), headers=NPZ)
    assert_problem(response, 422, "'vertices'", "float")
    assert client.get(f"/v1/actors/{grid_actor}").json() == before
