"""service.store.actors: the canonical neutral/layout/clip blobs, their loaders, the sample actor."""

from __future__ import annotations

import io
import json

import numpy as np
import pytest

from models_store import registry
from models_store.blobs import BlobStore
from models_store.db import make_session_factory, upgrade
from models_store.errors import NotFound
from service.store import actors as actor_store
from service.samples.uploads import sample_actor_uploads
from service.methods.inputs import InvalidInput
from service.samples import dataset

CLIPS = ("train_smile", "train_brow_raise")


@pytest.fixture(scope="module")
def uploads(pdm_actor_dir):
    return sample_actor_uploads(pdm_actor_dir, CLIPS)


@pytest.fixture
def store(tmp_path):
    url = f"sqlite:///{tmp_path / 'facesynth.db'}"
    upgrade(url)
    sessions = make_session_factory(url)
    with sessions() as session:
        yield session, BlobStore(tmp_path / "blobs")
    sessions.kw["bind"].dispose()


def _npz(data: bytes) -> dict[str, np.ndarray]:
    with np.load(io.BytesIO(data), allow_pickle=False) as d:
        return {k: d[k] for k in d.files}


def _upload(session, blobs, neutral: bytes, layout: bytes, clips: dict[str, bytes]):
    actor = actor_store.actor_from_blobs(neutral, layout)
    row = registry.create_actor(session, "sample")
    registry.set_neutral(session, blobs, row.id, neutral, vertex_count=actor.n_vertices,
                         triangle_count=len(actor.faces))
    registry.set_markers(session, blobs, row.id, layout, marker_count=actor.n_markers)
    clip_ids = [registry.add_clip(session, blobs, row.id, data, name=name,
                                  frames=len(_npz(data)["markers"])).id
                for name, data in clips.items()]
    return row.id, clip_ids


# ---------------------------------------------------------------------------- formats
def test_sample_actor_uploads_are_in_the_canonical_formats(uploads):
    neutral, layout, clips = uploads
    n = _npz(neutral)
    assert n["vertices"].dtype == np.float64 and n["vertices"].shape[1] == 3
    assert n["faces"].dtype == np.int64 and n["uv_faces"].shape == n["faces"].shape
    assert {k for k in n if k.startswith("region_")} == {"region_narrow_face", "region_face",
                                                         "region_head"}
    body = json.loads(layout)
    assert set(body) == {"names", "triangle", "barycentric"}
    assert len(body["names"]) == len(body["triangle"]) == len(body["barycentric"]) == 150
    assert set(clips) == set(CLIPS)
    c = _npz(clips["train_smile"])
    assert c["vertices"].dtype == c["markers"].dtype == np.float32
    assert c["displacement"].dtype == c["albedo"].dtype == np.float32
    assert c["markers"].shape[1:] == (150, 3) and float(c["fps"]) > 0


def test_stored_sample_actor_loads_exactly_as_the_dataset_loader(store, uploads, pdm_actor_dir):
    """Store round trip: the job's inputs equal what the methods' tests train on."""
    session, blobs = store
    actor_id, clip_ids = _upload(session, blobs, *uploads)
    actor = actor_store.load_actor_data(session, blobs, actor_id)
    expected = dataset.load_actor(pdm_actor_dir)
    for name in ("vertices", "faces", "uv", "uv_faces", "marker_triangle", "marker_barycentric"):
        assert np.array_equal(getattr(actor, name), getattr(expected, name)), name
        assert getattr(actor, name).dtype == getattr(expected, name).dtype, name
    assert actor.marker_names == expected.marker_names
    assert actor.regions.keys() == expected.regions.keys()
    assert all(np.array_equal(actor.regions[k], expected.regions[k]) for k in expected.regions)

    clips = actor_store.load_clips(session, blobs, clip_ids[::-1], actor)
    assert [c.name for c in clips] == list(CLIPS[::-1])
    for clip in clips:
        ref = dataset.load_clip(pdm_actor_dir, clip.name, expected)
        for name in ("vertices", "markers", "displacement", "albedo"):
            assert np.array_equal(getattr(clip, name), getattr(ref, name)), (clip.name, name)
        assert clip.fps == ref.fps


def test_per_vertex_uv_becomes_uv_faces():
    V = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0.]])
    F = np.array([[0, 1, 2]])
    n = _npz(actor_store.neutral_npz(V, F, V[:, :2]))
    assert np.array_equal(n["uv_faces"], F) and n["uv"].shape == (3, 2)


@pytest.mark.parametrize("change, message", [
    (dict(faces=np.array([[0, 1, 3]])), "face 0 references vertex 3 but the neutral has 3 vertices"),
    (dict(vertices=np.array([[0, 0, 0], [1, 0, 0], [0, np.nan, 0.]])), "non-finite"),
    (dict(uv=np.zeros((2, 2))), "per-vertex uv must have one row per vertex (3)"),
    (dict(regions={"bad name": np.ones(3, bool)}), "region name 'bad name'"),
    (dict(regions={"lips": np.ones(4, bool)}), "region 'lips' has 4 vertices (axis 0) but neutral vertices has 3"),
])
def test_neutral_npz_rejects_bad_meshes(change, message):
    args = dict(vertices=np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0.]]), faces=np.array([[0, 1, 2]]),
                uv=np.zeros((3, 2)))
    args.update(change)
    with pytest.raises(InvalidInput, match=message.replace("(", r"\(").replace(")", r"\)")):
        actor_store.neutral_npz(**args)


@pytest.mark.parametrize("names, bary, message", [
    (["A", "A"], [[1, 0, 0], [0, 1, 0]], "marker name 'A' appears more than once"),
    (["A", "B"], [[1, 0, 0], [0.5, 0.6, 0]], "marker 'B' has barycentric"),
    (["A", "B"], [[1, 0, 0]], r"has shape \(1, 3\), expected \(2, 3\)"),
])
def test_layout_json_rejects_bad_layouts(names, bary, message):
    with pytest.raises(InvalidInput, match=message):
        actor_store.layout_json(names, np.zeros(len(names), np.int64), np.array(bary, float))


def test_clip_npz_keeps_nan_markers_and_rejects_inconsistent_frames():
    V, P = np.zeros((2, 4, 3)), np.zeros((2, 5, 3))
    P[1, 2] = np.nan
    clip = actor_store.clip_from_blob(actor_store.clip_npz(V, P, fps=24.0), "c")
    assert np.isnan(clip.markers[1, 2]).all() and clip.fps == 24.0 and clip.displacement is None
    with pytest.raises(InvalidInput, match=r"clip markers has shape \(1, 5, 3\), expected \(2, M, 3\)"):
        actor_store.clip_npz(V, P[:1])
    with pytest.raises(InvalidInput, match=r"clip displacement has shape \(3, 8, 8\), expected \(2, H, W\)"):
        actor_store.clip_npz(V, P, displacement=np.zeros((3, 8, 8)))
    with pytest.raises(InvalidInput, match="clip frame 0 vertex 0 has a non-finite coordinate"):
        actor_store.clip_npz(np.full((1, 4, 3), np.inf), P[:1])


# ---------------------------------------------------------------------------- loaders
def test_load_actor_without_neutral_is_invalid_input(store):
    session, blobs = store
    actor = registry.create_actor(session, "empty")
    with pytest.raises(InvalidInput, match="has no neutral yet"):
        actor_store.load_actor_data(session, blobs, actor.id)
    with pytest.raises(NotFound):
        actor_store.load_actor_data(session, blobs, "act_01m84g72zv56qgast3a85c8cy8")


def test_load_clips_rejects_a_clip_with_the_wrong_marker_count(store, uploads):
    session, blobs = store
    neutral, layout, clips = uploads
    c = _npz(clips["train_smile"])
    short = actor_store.clip_npz(c["vertices"], c["markers"][:, :149])
    actor_id, clip_ids = _upload(session, blobs, neutral, layout, {"short": short})
    actor = actor_store.load_actor_data(session, blobs, actor_id)
    with pytest.raises(InvalidInput, match=r"clip 'short': markers must be \(F,150,3\)"):
        actor_store.load_clips(session, blobs, clip_ids, actor)


def test_a_corrupt_clip_blob_is_invalid_input():
    with pytest.raises(InvalidInput, match="clip 'x' is not a readable .npz"):
        actor_store.clip_from_blob(b"not a zip", "x")
    with pytest.raises(InvalidInput, match=r"clip 'y' lacks \['markers'\]"):
        buffer = io.BytesIO()
        np.savez(buffer, vertices=np.zeros((1, 3, 3)))
        actor_store.clip_from_blob(buffer.getvalue(), "y")


def test_load_clips_takes_clips_with_and_without_maps(store, uploads):
    """Whether every clip must carry maps when some do is the method's rule (shape space
    uses maps where clips have them; issue 17 item 6), not the loader's."""
    from service.methods.inputs import check_clips

    session, blobs = store
    neutral, layout, clips = uploads
    c = _npz(clips["train_smile"])
    bare = actor_store.clip_npz(c["vertices"], c["markers"])
    actor_id, clip_ids = _upload(session, blobs, neutral, layout,
                                 {"train_smile": clips["train_smile"], "bare": bare})
    actor = actor_store.load_actor_data(session, blobs, actor_id)
    loaded = actor_store.load_clips(session, blobs, clip_ids, actor)
    assert loaded[0].albedo is not None and loaded[1].albedo is None
    with pytest.raises(InvalidInput, match="every clip or for none"):
        check_clips(actor, loaded)                     # the strict rule of the other methods
