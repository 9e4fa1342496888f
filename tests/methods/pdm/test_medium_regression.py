"""PdmParams.medium_regression (issue 17): the mesh's medium offsets from the marker regression
(service.geometry.marker_regression) instead of the medium polynomial, on the level-0 actor."""

import numpy as np
import pytest

from service.methods.pdm.model import PdmModel, PdmParams, train
from service.samples import dataset
from tests.methods.pdm.test_model import _face_error, _thin_shell_only

#: small bands: only the mesh path differs from the session's pdm_model (same clips)
SMALL = dict(medium_resolution=64, fine_resolution=128)


@pytest.fixture(scope="module")
def pair(pdm_data, pdm_model):
    """(the session's polynomial model, medium_regression = None; a model with the default
    medium_regression trained on the same clips)."""
    actor, clips = pdm_data
    assert pdm_model.data.params.medium_regression is None and PdmParams().medium_regression == 4.0
    return pdm_model, train(actor, clips, PdmParams(**SMALL))


def test_the_neutral_is_reproduced_and_the_regression_is_what_the_mesh_adds(pair, pdm_data):
    """Rest markers give the thin shell of the detailed neutral (the regression passes
    through the neutral); any frame's mesh is the smooth thin shell plus the regression's
    offsets, head pose put back; the maps are the polynomial model's."""
    poly, reg = pair
    actor, clips = pdm_data
    rest = actor.marker_positions()[None]
    out = reg.synthesize(rest, outputs=("mesh",))
    assert np.abs(out["vertices"][0] - _thin_shell_only(reg, actor, rest)[0]).max() < 2e-4   # float32
    markers = clips[2].markers[[5, 12]]
    ev = reg.evaluator
    pose, u_H, _ = ev.deformation(markers)
    want = pose.restore(ev.base.deform(u_H) + reg.data.medium_regression(u_H))
    got = reg.synthesize(markers, outputs=("mesh", "displacement"))
    np.testing.assert_allclose(got["vertices"], want, atol=1e-4)
    assert got["displacement"].shape == poly.synthesize(markers, outputs=("displacement",))["displacement"].shape


def test_held_out_frames_are_closer_than_the_polynomial_and_the_thin_shell(pair, pdm_actor_dir, pdm_data):
    """On the held-out in-range performance the regression's mesh is closer to the truth than
    the medium polynomial's trained on the same frames, mean and max over the face, and no
    frame's max exceeds the thin shell's."""
    poly, reg = pair
    actor, _ = pdm_data
    frames = dataset.map_frames(pdm_actor_dir, "heldout_in_range")
    clip = dataset.load_clip(pdm_actor_dir, "heldout_in_range", actor, frames=frames)
    e_poly = _face_error(poly.synthesize(clip.markers, outputs=("mesh",))["vertices"], clip.vertices, actor)
    e_reg = _face_error(reg.synthesize(clip.markers, outputs=("mesh",))["vertices"], clip.vertices, actor)
    e_shell = _face_error(_thin_shell_only(reg, actor, clip.markers), clip.vertices, actor)
    # measured with s = 2 (session 18): mean 0.202 (polynomial) / 0.118 (regression) / 0.274 mm (thin shell)
    assert e_reg.mean() < 0.9 * e_poly.mean()
    assert e_reg.max() < e_poly.max()
    assert np.all(e_reg.max(axis=1) <= e_shell.max(axis=1))


def test_the_regression_round_trips_bit_for_bit(pair, pdm_data, tmp_path):
    poly, reg = pair
    _, clips = pdm_data
    reg.save(tmp_path / "reg")
    poly.save(tmp_path / "poly")
    back = PdmModel.load(tmp_path / "reg")
    a, b = reg.data.medium_regression, back.data.medium_regression
    for k in ("Pq", "scale", "Q", "mean_u", "mean_y"):
        np.testing.assert_array_equal(getattr(a, k), getattr(b, k))
    assert b.Pq.dtype == np.int16 and b.Q.dtype == np.float32
    markers = clips[0].markers[[3, 9]]
    np.testing.assert_array_equal(back.synthesize(markers, outputs=("mesh",))["vertices"],
                                  reg.synthesize(markers, outputs=("mesh",))["vertices"])
    with np.load(tmp_path / "poly" / "model.npz") as z:
        assert not any(k.startswith("medium_regression") for k in z.files)
    assert PdmModel.load(tmp_path / "poly").data.medium_regression is None


def test_the_regression_mesh_needs_no_compiled_shell_mesh(pair, pdm_data, tmp_path):
    """The regression's mesh is the base surface (``base.deform``: the basis in vertex order)
    plus its offsets: the evaluator builds no ShellMesh (its reordered bases, 2 × (n,M)
    float32, and frames; issue 23: the model cache weighed them though no frame reads
    them). Loaded, the default model's cache weight is within 10 % of the resident cost of
    loading it and synthesizing every output of two training frames and one beyond the
    training (where the detail fades; the polynomial model's on a neutral frame:
    tests/methods/test_footprint.py)."""
    from tests.methods.test_footprint import resident_cost

    poly, reg = pair
    actor, clips = pdm_data
    rest = actor.marker_positions()
    assert reg.evaluator.shell_mesh is None and poly.evaluator.shell_mesh is not None
    reg.save(tmp_path / "reg")
    with np.load(tmp_path / "reg" / "cache.npz") as z:
        assert not any(k.startswith("op_shell_mesh_") for k in z.files)
    frames = np.concatenate([clips[1].markers[[4, 11]], rest + 2.0 * (clips[2].markers[[9]] - rest)])
    cost = resident_cost("pdm", tmp_path / "reg", frames)
    assert cost["measured"] > 4 << 20, cost
    assert abs(cost["estimate"] / cost["measured"] - 1) <= 0.10, cost
