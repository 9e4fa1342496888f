"""POST /v1/actors/{id}/tracking-jobs: the upload's checks, each bad input a 4xx naming what
is wrong, and a good upload (image sequences or one video per view) stored and queued."""

from __future__ import annotations

import io
import json
import zipfile

import cv2
import numpy as np
import pytest

from models_store import registry
from service.io.npz import npz_bytes
from service.samples.tracking_scene import build_tracking_scene, tracking_uploads
from tests.api.conftest import assert_problem

NPZ = {"Content-Type": "application/x-npz"}


@pytest.fixture(scope="module")
def scene():
    return build_tracking_scene(frames=4, views=2, size=32, k=8)


@pytest.fixture
def cap_actor(client, actor_id, scene) -> str:
    response = client.put(f"/v1/actors/{actor_id}/neutral", headers=NPZ,
                          content=npz_bytes(vertices=scene.artist_vertices, faces=scene.faces,
                                            uv=scene.uv))
    assert response.status_code == 200, response.text
    return actor_id


def parts(scene, **replace):
    """The scene's upload with some parts replaced (a value None drops the part)."""
    out = [(name, value) for name, value in tracking_uploads(scene) if name not in replace]
    for name, value in replace.items():
        if value is not None:
            out.extend((name, v) for v in (value if isinstance(value, list) else [value]))
    return out


def post(client, actor, files, **data):
    return client.post(f"/v1/actors/{actor}/tracking-jobs", files=files, data=data or None)


def cameras_json(scene, **change) -> tuple:
    views = [{"name": f"v{c}", **cam.to_json()} for c, cam in enumerate(scene.cameras)]
    for key, value in change.items():
        views[0][key] = value
    return ("cameras.json", json.dumps({"views": views}).encode(), "application/json")


def zipped(members: dict[str, bytes], name: str) -> tuple:
    buffer = io.BytesIO()
    with zipfile.ZipFile(buffer, "w") as archive:
        for member, data in members.items():
            archive.writestr(member, data)
    return (name, buffer.getvalue(), "application/zip")


def png(image) -> bytes:
    return cv2.imencode(".png", np.asarray(image, np.uint8))[1].tobytes()


def test_a_good_upload_is_stored_and_queued(client, cap_actor, scene, submitted):
    services = client.app.state.services
    response = post(client, cap_actor, parts(scene), params=json.dumps({"candidate_stride": 2}))
    assert response.status_code == 202, response.text
    job_id = response.json()["job_id"]
    assert response.headers["location"] == f"/v1/jobs/{job_id}"
    assert submitted == [job_id]
    job = client.get(f"/v1/jobs/{job_id}").json()
    assert job["kind"] == "track" and job["status"] == "queued"
    with services.session() as session:
        payload = registry.get_job(session, job_id).payload
    assert payload["frames"] == 4 and payload["views"] == ["v0", "v1"]
    assert payload["scans"] == ["scan0", "scan1"] and payload["params"]["candidate_stride"] == 2
    frames = np.load(services.blobs.path(payload["frames_blob"]))
    np.testing.assert_array_equal(frames, scene.frame_images)        # PNG is lossless


def test_one_video_per_view_is_decoded_with_opencv(client, cap_actor, scene, tmp_path):
    services = client.app.state.services
    videos = []
    for c in range(2):
        path = tmp_path / f"v{c}.avi"
        writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 30, (32, 32), False)
        for t in range(4):
            writer.write(scene.frame_images[t, c])
        writer.release()
        videos.append((path.name, path.read_bytes(), "video/x-msvideo"))
    response = post(client, cap_actor, parts(scene, frames=videos))
    assert response.status_code == 202, response.text
    with services.session() as session:
        payload = registry.get_job(session, response.json()["job_id"]).payload
    frames = np.load(services.blobs.path(payload["frames_blob"])).astype(float)
    assert frames.shape == (4, 2, 32, 32)
    # MJPG is lossy: within a few grey levels of the rendered frames on average
    assert np.abs(frames - scene.frame_images).mean() < 4.0


@pytest.mark.parametrize("change, fragments", [
    (dict(R=[[1, 0, 0], [0, 1, 0], [0, 0, 2]]), ("cameras.views[0].R is not a rotation",)),
    (dict(K=[[1, 0], [0, 1]]), ("cameras.views.0.K", "3×3")),
    (dict(K=[[-5, 0, 16], [0, 5, 16], [0, 0, 1]]), ("fx, fy > 0",)),
    (dict(width=40), ("same image size",)),
    (dict(t=[0, 0]), ("cameras.views.0.t",)),
])
def test_a_bad_calibration_is_a_422_naming_it(client, cap_actor, scene, change, fragments):
    assert_problem(post(client, cap_actor, parts(scene, cameras=cameras_json(scene, **change))),
                   422, *fragments)


def test_images_of_another_size_than_the_calibration_are_a_422(client, cap_actor, scene):
    views = [{"name": f"v{c}", **cam.scaled(1.5).to_json()} for c, cam in enumerate(scene.cameras)]
    cams = ("c.json", json.dumps({"views": views}).encode(), "application/json")
    assert_problem(post(client, cap_actor, parts(scene, cameras=cams)), 422,
                   "is 32×32 pixels; the calibration says 48×48")


def test_mismatched_views_and_frame_counts_are_a_422(client, cap_actor, scene):
    only_v0 = zipped({f"v0/{t}.png": png(scene.frame_images[t, 0]) for t in range(4)}, "f.zip")
    assert_problem(post(client, cap_actor, parts(scene, frames=only_v0)), 422,
                   "no images for view(s) ['v1']")
    uneven = zipped({**{f"v0/{t}.png": png(scene.frame_images[t, 0]) for t in range(4)},
                     **{f"v1/{t}.png": png(scene.frame_images[t, 1]) for t in range(3)}}, "f.zip")
    assert_problem(post(client, cap_actor, parts(scene, frames=uneven)), 422,
                   "different frame counts: v0 4, v1 3")
    stray = zipped({**{f"v{c}/{t}.png": png(scene.frame_images[t, c]) for t in range(4)
                       for c in range(2)}, "v7/0.png": png(scene.frame_images[0, 0])}, "f.zip")
    assert_problem(post(client, cap_actor, parts(scene, frames=stray)), 422,
                   "folder(s) ['v7'] name no view")
    one = zipped({f"v{c}/0.png": png(scene.frame_images[0, c]) for c in range(2)}, "f.zip")
    assert_problem(post(client, cap_actor, parts(scene, frames=one)), 422, "at least 2 frames")


def test_videos_must_be_readable_and_one_per_view(client, cap_actor, scene):
    junk = ("v0.mp4", b"not a video at all", "video/mp4")
    assert_problem(post(client, cap_actor, parts(scene, frames=[junk, junk])), 422,
                   "video 'v0.mp4' (view 'v0')", "OpenCV cannot decode")
    assert_problem(post(client, cap_actor, parts(scene, frames=[junk])), 422,
                   "1 video file(s) for 2 calibrated view(s)")
    assert_problem(post(client, cap_actor, parts(scene, frames=("f.txt", b"x", "text/plain"))),
                   422, "neither one .zip of image sequences nor video files")


def test_bad_scans_images_and_params_are_a_422(client, cap_actor, scene):
    assert_problem(post(client, cap_actor, parts(scene, scans=None)), 422, "'scans' parts")
    assert_problem(post(client, cap_actor, parts(scene, scans=("s.stl", b"solid", "model/stl"))),
                   422, "is not .obj or .ply")
    assert_problem(post(client, cap_actor, parts(scene, scans=("s.obj", b"v 1 2\nf 1 2 3\n",
                                                               "model/obj"))), 422)
    missing = zipped({"scan0/v0.png": png(scene.scan_images[0, 0])}, "i.zip")
    assert_problem(post(client, cap_actor, parts(scene, scan_images=missing)), 422,
                   "no image of scan 'scan0' in view 'v1'")
    broken = zipped({f"scan{s}/v{c}.png": b"\x89PNG\r\n\x1a\nbroken-broken-broken"
                     for s in range(2) for c in range(2)}, "i.zip")
    assert_problem(post(client, cap_actor, parts(scene, scan_images=broken)), 422,
                   "scan_images/scan0/v0.png")
    assert_problem(post(client, cap_actor, parts(scene, scan_images=("i.zip", b"PK?", "application/zip"))),
                   422, "scan_images is not a readable zip")
    assert_problem(post(client, cap_actor, parts(scene), params='{"hat_slope": 7}'), 422,
                   "params: hat_slope")
    assert_problem(post(client, cap_actor, parts(scene), params="[1]"), 422, "JSON object")
    assert_problem(post(client, cap_actor, parts(scene, cameras=None)), 422, "'cameras' part")
    assert_problem(post(client, cap_actor, parts(scene, extra=("x.bin", b"1", "a/b"))), 422,
                   "unknown part(s) ['extra']")


def test_no_neutral_is_a_409_and_a_json_body_a_415(client, actor_id, scene):
    assert_problem(post(client, actor_id, parts(scene)), 409, "no neutral mesh")
    response = client.post(f"/v1/actors/{actor_id}/tracking-jobs", json={"cameras": []})
    assert_problem(response, 415, "multipart/form-data")
    assert_problem(post(client, "act_00000000000000000000000000", parts(scene)), 404)
