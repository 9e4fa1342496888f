"""Capture defects: the noise has the stated σ, occlusions come in runs, variants keep the truth."""

import numpy as np

from service.samples import capture_noise as cn


def _tracks(frames=300, markers=60, seed=0):
    rng = np.random.default_rng(seed)
    return rng.uniform(-80, 80, (1, markers, 3)) + np.cumsum(rng.normal(0, 0.2, (frames, markers, 3)), axis=0)


def test_noise_has_the_stated_sigma_per_coordinate():
    X = _tracks()
    noisy = cn.noisy_markers(X, 0.3, np.random.default_rng(5))
    e = noisy - X
    # 54 000 samples: the standard error of the sample σ is 0.3/√(2·54000) ≈ 0.0009 mm
    assert abs(e.std() - 0.3) < 0.004 and abs(e.mean()) < 0.005
    np.testing.assert_allclose(e.std(axis=(0, 1)), 0.3, atol=0.006)          # isotropic
    np.testing.assert_allclose(np.sqrt((e ** 2).sum(-1).mean()), 0.3 * np.sqrt(3), rtol=0.01)
    again = cn.noisy_markers(X, 0.3, np.random.default_rng(5))
    np.testing.assert_array_equal(noisy, again)


def test_noise_keeps_occluded_markers_missing():
    X = _tracks(10, 5)
    X[3, 2] = np.nan
    assert np.isnan(cn.noisy_markers(X, 0.3, np.random.default_rng(1))[3, 2]).all()


def test_occlusions_come_in_runs_and_respect_the_cap():
    X = _tracks()
    mask = cn.occlusion_mask(X, 30.0, np.random.default_rng(2))
    assert 0.02 < mask.mean() < 0.3
    assert mask.sum(axis=1).max() <= int(cn.MAX_OCCLUDED_FRACTION * X.shape[1])
    # runs: mean length of the occluded stretches of a marker is several frames
    starts = (mask[1:] & ~mask[:-1]).sum() + mask[0].sum()
    assert mask.sum() / starts >= cn.DROPOUT_FRAMES[0]
    occluded = cn.occluded_markers(X, mask)
    assert np.array_equal(np.isnan(occluded).all(-1), mask)
    np.testing.assert_array_equal(occluded[~mask], X[~mask])


def test_variants_scale_sigma_with_the_unit_and_keep_the_clean_markers():
    X = _tracks(200, 40)
    mm = cn.marker_variants(X, 30.0, 1.0, seed=3, salt=cn.variant_salt("p"))
    cm = cn.marker_variants(X * 0.1, 30.0, 0.1, seed=3, salt=cn.variant_salt("p"))
    assert mm["noisy"]["info"]["marker_noise_sigma"] == 0.3
    assert cm["noisy"]["info"]["marker_noise_sigma"] == 0.3 * 0.1
    np.testing.assert_allclose(cm["noisy"]["markers"], mm["noisy"]["markers"] * 0.1, rtol=1e-6, atol=1e-6)
    arrays = {"markers": X.astype(np.float32), "vertices": np.zeros(3)}
    v = cn.variant_arrays(arrays, mm["occluded"]["markers"])
    assert v["markers_clean"] is arrays["markers"] and v["vertices"] is arrays["vertices"]
    assert np.isnan(v["markers"]).any() and not np.isnan(v["markers_clean"]).any()
