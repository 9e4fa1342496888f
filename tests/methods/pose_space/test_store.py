"""Tests for service.methods.pose_space.store: the model directory round trip."""

import numpy as np
import pytest

from service.methods.model_dir import ModelCorrupt
from service.methods.pose_space import PoseSpaceModel
from tests.methods.prior_modes import check_marker_modes
from tests.methods.verified import load_verified_without_hashing

OUT = ("mesh", "mesh_detailed", "displacement", "normal_map")


@pytest.mark.parametrize("which", ["wpsd_exact", "psd_lsq", "wpsd_regression"])
def test_save_load_round_trip_is_bit_exact(which, request, ps_data, tmp_path):
    model = request.getfixturevalue(which)
    _, clips = ps_data
    manifest = model.save(tmp_path / "m")
    assert manifest["kind"] == model.kind and "cache.npz" in manifest["derived"]
    loaded = PoseSpaceModel.load(tmp_path / "m")
    assert loaded.params == model.params and loaded.metrics == model.metrics
    markers = clips[1].markers[[2, 9]]
    a, b = model.synthesize(markers, OUT), loaded.synthesize(markers, OUT)
    for k in a:
        assert np.array_equal(a[k], b[k]), k
    # the learned marker prior (issue 17) round-trips
    assert model.evaluator.base.marker_prior is not None
    np.testing.assert_array_equal(loaded.evaluator.base.marker_prior.covariance,
                                  model.evaluator.base.marker_prior.covariance)
    base = loaded.evaluator.base
    check_marker_modes(loaded.marker_modes, base.rest_markers, base.marker_prior, loaded.data.pose_weights)
    # without the derived cache the basis is recomputed: the same numbers
    (tmp_path / "m" / "cache.npz").unlink()
    import json
    man = json.loads((tmp_path / "m" / "manifest.json").read_text())
    man["derived"] = {}
    (tmp_path / "m" / "manifest.json").write_text(json.dumps(man))
    c = PoseSpaceModel.load(tmp_path / "m").synthesize(markers, ("mesh",))
    np.testing.assert_allclose(c["vertices"], a["vertices"], atol=1e-5)


def test_load_rejects_a_changed_file(wpsd_exact, tmp_path):
    wpsd_exact.save(tmp_path / "m")
    with open(tmp_path / "m" / "model.npz", "r+b") as f:
        f.seek(200)
        f.write(b"\x00\x01")
    with pytest.raises(ModelCorrupt, match="checksum"):
        PoseSpaceModel.load(tmp_path / "m")


def test_a_directory_the_blob_store_verified_is_not_hashed_again(wpsd_exact, ps_data, tmp_path, monkeypatch):
    wpsd_exact.save(tmp_path / "m")
    loaded = load_verified_without_hashing(PoseSpaceModel.load, tmp_path / "m", monkeypatch)
    markers = ps_data[1][1].markers[[2, 9]]
    assert np.array_equal(loaded.synthesize(markers, ("mesh",))["vertices"],
                          wpsd_exact.synthesize(markers, ("mesh",))["vertices"])


def test_a_model_stored_before_the_marker_regression_existed_loads_without_it(wpsd_exact, tmp_path):
    """Its manifest's params lack the field: it loads as bickel2008's WPSD (null), not as
    today's default (s = 3), and equals the model it was."""
    import json

    from service.methods.pose_space import WpsdParams

    assert WpsdParams().marker_regression == 3.0 and wpsd_exact.params.marker_regression is None
    wpsd_exact.save(tmp_path / "m")
    man = json.loads((tmp_path / "m" / "manifest.json").read_text())
    del man["params"]["marker_regression"]
    (tmp_path / "m" / "manifest.json").write_text(json.dumps(man))
    loaded = PoseSpaceModel.load(tmp_path / "m")
    assert loaded.params == wpsd_exact.params and loaded.evaluator.data.regression is None
