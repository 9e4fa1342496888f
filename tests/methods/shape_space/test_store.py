"""Tests for service.methods.shape_space.store: the model directory round trip and its checks."""

import json

import numpy as np
import pytest

from service.methods.shape_space import ShapeSpaceModel
from service.methods.model_dir import ModelCorrupt
from tests.methods.prior_modes import check_marker_modes
from tests.methods.verified import load_verified_without_hashing


@pytest.fixture(scope="module")
def saved(shape_space_model, tmp_path_factory):
    path = tmp_path_factory.mktemp("shape_space_store") / "model"
    return path, shape_space_model.save(path)


def test_round_trip_is_bit_exact(shape_space_model, shape_space_data, saved):
    path, manifest = saved
    loaded = ShapeSpaceModel.load(path)
    _, clip, heldout = shape_space_data
    frames = np.stack([heldout["vertices_medium"][40], clip.vertices[123]])
    a = shape_space_model.enhance(frames, outputs=("mesh", "displacement", "albedo"))
    b = loaded.enhance(frames, outputs=("mesh", "displacement", "albedo"))
    assert {"fine_displacement", "albedo"} <= a.keys()
    assert a.keys() == b.keys()
    for key in a:
        np.testing.assert_array_equal(a[key], b[key], err_msg=key)
    markers = heldout["markers"][[40]]
    a, b = shape_space_model.enhance(markers), loaded.enhance(markers)
    for key in ("vertices", "corrected_input"):
        np.testing.assert_array_equal(a[key], b[key], err_msg=key)
    for key in ("shapes", "gram", "corrections"):
        np.testing.assert_array_equal(getattr(loaded.marker_database, key),
                                      getattr(shape_space_model.marker_database, key), err_msg=key)
    for key in ("shapes", "detail", "gram", "region_weights", "patches", "align_weights"):
        np.testing.assert_array_equal(getattr(loaded, key), getattr(shape_space_model, key), err_msg=key)
    assert loaded.params == shape_space_model.params
    # the learned marker prior (issue 17) round-trips
    assert shape_space_model.data.marker_prior is not None
    np.testing.assert_array_equal(loaded.data.marker_prior.covariance, shape_space_model.data.marker_prior.covariance)
    shell = loaded.evaluator.shell
    check_marker_modes(loaded.marker_modes, shell.rest, loaded.data.marker_prior, shell.weights)
    assert manifest["kind"] == "shape_space" and manifest["region_names"] == list(loaded.region_names)
    assert manifest["size_bytes"] == sum(p.stat().st_size for p in path.iterdir()
                                         if p.name != "manifest.json")


def test_altered_file_is_refused(saved, tmp_path):
    path, _ = saved
    copy = tmp_path / "copy"
    copy.mkdir()
    for f in path.iterdir():
        (copy / f.name).write_bytes(f.read_bytes())
    data = bytearray((copy / "detail.npz").read_bytes())
    data[-100] ^= 0xFF
    (copy / "detail.npz").write_bytes(bytes(data))
    with pytest.raises(ModelCorrupt, match="checksum"):
        ShapeSpaceModel.load(copy)
    (copy / "detail.npz").unlink()
    with pytest.raises(ModelCorrupt, match="missing"):
        ShapeSpaceModel.load(copy)


def test_other_kinds_are_refused(saved, tmp_path):
    path, manifest = saved
    (tmp_path / "manifest.json").write_text(json.dumps({**manifest, "kind": "pdm"}))
    with pytest.raises(ModelCorrupt, match="not a shape_space model"):
        ShapeSpaceModel.load(tmp_path)
    with pytest.raises(ModelCorrupt, match="manifest"):
        ShapeSpaceModel.load(tmp_path / "nowhere")


def test_texel_major_maps_of_an_older_model_load_frame_major(saved, tmp_path):
    """Models stored before the database maps were frame-major hold them texel-major (F
    order): they load frame-major (a request reads whole frames) with the same values, and
    the rest of the database stays mapped from its files."""
    from service.io.atomic import write_npz
    from service.io.npz import npz_mapped
    from service.methods.footprint import file_mapped

    path, _ = saved
    old = tmp_path / "old"
    old.mkdir()
    for f in path.iterdir():
        (old / f.name).write_bytes(f.read_bytes())
    arrays = {k: np.asfortranarray(v) if k in ("displacement", "albedo") else v
              for k, v in npz_mapped(old / "maps.npz").items()}
    manifest = json.loads((old / "manifest.json").read_text())
    manifest["files"]["maps.npz"] = write_npz(old / "maps.npz", arrays)
    (old / "manifest.json").write_text(json.dumps(manifest))
    assert not npz_mapped(old / "maps.npz")["displacement"].flags.c_contiguous
    a, b = ShapeSpaceModel.load(path), ShapeSpaceModel.load(old)
    for attr in ("fine_maps", "albedo_maps"):
        m = getattr(b.data, attr).maps
        assert m.flags.c_contiguous and not file_mapped(m)
        np.testing.assert_array_equal(m, getattr(a.data, attr).maps)
    assert file_mapped(b.data.detail)


def test_a_directory_the_blob_store_verified_is_not_hashed_again(shape_space_model, saved, monkeypatch):
    path, _ = saved
    loaded = load_verified_without_hashing(ShapeSpaceModel.load, path, monkeypatch)
    assert loaded.metrics == shape_space_model.metrics
