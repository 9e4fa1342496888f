"""service/app/marker_units.py: spread ratios (hand-computed), the band, the unit named."""

from __future__ import annotations

import numpy as np
import pytest

from service.app.marker_units import (SPREAD_BAND, check_marker_units, face_unit, rms_spread,
                                      spread_ratios)
from service.methods.inputs import InvalidInput

#: four markers on a square of side 2 mm about (1,1,0): each is √2 from the centroid
SQUARE = np.array([[0, 0, 0], [2, 0, 0], [2, 2, 0], [0, 2, 0]], dtype=float)


def _rotation(angle: float) -> np.ndarray:
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]])


def test_spread_is_the_rms_distance_from_the_centroid():
    assert rms_spread(SQUARE) == pytest.approx(np.sqrt(2))
    assert rms_spread(np.vstack([SQUARE, [[np.nan] * 3]])) == pytest.approx(np.sqrt(2))


def test_ratio_ignores_rigid_motion_and_compares_the_visible_markers():
    moved = SQUARE @ _rotation(0.7).T + [100.0, -40.0, 7.0]
    scaled = 0.001 * SQUARE
    occluded = SQUARE.copy()
    occluded[3] = np.nan          # the other three: centroid (4/3, 2/3), spread √(16/9)... same in both
    few = np.full_like(SQUARE, np.nan)
    few[0] = 0.0
    ratios = spread_ratios(np.stack([moved, scaled, occluded, few]), SQUARE)
    np.testing.assert_allclose(ratios, [1.0, 0.001, 1.0])       # the 1-marker frame is skipped


def test_frames_with_every_marker_visible_give_the_masked_ratios():
    """The all-visible shortcut against the masked formula (forced by one occluded frame
    appended), and the hand-computed ratio of a rigidly moved and a scaled square."""
    rng = np.random.default_rng(3)
    rest = rng.normal(scale=50.0, size=(30, 3))
    frames = rest * rng.uniform(0.5, 2.0, size=(6, 1, 1)) + rng.normal(size=(6, 30, 3))
    masked = np.concatenate([frames, np.full((1, 30, 3), np.nan)])
    np.testing.assert_allclose(spread_ratios(frames, rest), spread_ratios(masked, rest), rtol=1e-12)
    moved = SQUARE @ _rotation(0.3).T + 5.0
    np.testing.assert_allclose(spread_ratios(np.stack([moved, 3 * SQUARE]), SQUARE), [1.0, 3.0])
    assert len(spread_ratios(np.stack([SQUARE]), np.zeros((4, 3)))) == 0   # a layout without spread


def test_a_face_in_band_passes_and_metres_for_millimetres_is_named():
    rng = np.random.default_rng(0)
    rest = rng.normal(scale=60.0, size=(40, 3))                  # a layout spread ~100 mm
    frames = rest + rng.normal(scale=3.0, size=(5, 40, 3))       # expressions: a few mm
    check_marker_units(frames, rest, "mm")
    check_marker_units(frames * 0.5, rest, "mm")                 # a factor 2: inside the band
    with pytest.raises(InvalidInput) as error:
        check_marker_units(frames / 1000, rest, "mm")
    message = str(error.value)
    assert "were they sent in metres?" in message and "about 998× smaller" in message
    assert f"{rms_spread(rest):.3g} mm" in message
    with pytest.raises(InvalidInput, match="centimetres"):
        check_marker_units(frames / 10, rest, "mm")
    with pytest.raises(InvalidInput, match="larger; were they sent in millimetres"):
        check_marker_units(frames * 1000, rest, "m")
    with pytest.raises(InvalidInput, match="inches"):
        check_marker_units(frames / 25.4, rest, "mm")


def test_band_edges_and_unknown_unit():
    rest = SQUARE * 30
    low, high = SPREAD_BAND
    check_marker_units(rest[None] * low * 1.01, rest)
    check_marker_units(rest[None] * high * 0.99, rest)
    with pytest.raises(InvalidInput):
        check_marker_units(rest[None] * low * 0.99, rest)
    with pytest.raises(InvalidInput) as error:                   # 5×: outside, no unit explains it
        check_marker_units(rest[None] * 5, rest)
    assert "were they" not in str(error.value)
    with pytest.raises(InvalidInput, match="units 100× larger than the actor's"):
        check_marker_units(rest[None] / 100, rest, None)


def test_the_actors_unit_is_declared_or_inferred_from_a_faces_size():
    face_mm = SQUARE * 50                                        # spread 70.7 mm
    assert face_unit(face_mm) == "mm"
    assert face_unit(face_mm / 10) == "cm" and face_unit(face_mm / 1000) == "m"
    assert face_unit(face_mm, "in") == "in"                      # declared wins
    assert face_unit(SQUARE) is None                             # 1.4: a face in no unit


def test_the_sample_actor_performances_are_in_band(pdm_actor_dir):
    """The band was chosen on the sample actors: every frame of a held-out performance is
    within a few percent of the layout's spread."""
    import json

    with np.load(pdm_actor_dir / "neutral.npz") as d:
        V, F = d["vertices"], d["faces"]
    layout = json.loads((pdm_actor_dir / "markers.json").read_text())["markers"]
    from service.app.marker_units import layout_positions
    rest = layout_positions(V, F, np.array([m["triangle"] for m in layout]),
                            np.array([m["barycentric"] for m in layout]))
    assert face_unit(rest) == "mm"
    with np.load(pdm_actor_dir / "performances" / "heldout_in_range.npz") as d:
        ratios = spread_ratios(d["markers"], rest)
    assert 0.95 < ratios.min() <= ratios.max() < 1.07
    check_marker_units(d_markers := np.load(pdm_actor_dir / "performances" / "heldout_in_range.npz")["markers"], rest, "mm")
    with pytest.raises(InvalidInput, match="metres"):
        check_marker_units(d_markers / 1000, rest, "mm")
