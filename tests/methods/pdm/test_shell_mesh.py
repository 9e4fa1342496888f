"""The PDM's per-frame medium mesh on the compiled shell kernels (service.methods.pdm.shell_mesh)
against a float64 reference: the thin-shell products in float64, FrameField's float64 frames,
the fallback and the composition in float64 (the validity evaluation as synthesis runs it)."""

from __future__ import annotations

import numpy as np
import pytest
from tests.methods.pdm.beyond import beyond

#: |fallback − float64| at the UV points relative to the largest |fallback| (measured 3.5e-5 –
#: 4.6e-5 on this model's frames, where the NumPy float32 path it replaced (BLAS products,
#: FrameField.rows32) measured 5.6e-5 – 7.5e-5: the float32 displacement's rounding (~1e-6 mm)
#: turns the frames of the smallest triangles (edges down to 0.03 mm) by ~5e-5)
FALLBACK_RTOL = 1e-4
#: |vertices − float64| (mm), frames inside and 2.5× beyond the hull (measured 1.0e-4 – 1.7e-4:
#: the fallback's and the frames' float32 rounding as above, the float32 output and head pose)
MESH_ATOL = 5e-4

def _float64_path(ev, markers):
    """World vertices (F,n,3) and the fallback (F,K,3) of the medium mesh in float64."""
    pose, u_H, S = ev.deformation(markers)
    X = ev.base.smooth + np.einsum("nm,fmc->fnc", ev.base.basis.astype(np.float64), u_H)
    frames = ev.base.frame_field.frames(X)                                     # (F,n,3,3) float64
    world = ev.shell_offset + np.einsum("nm,fmc->fnc", ev.shell_correction.astype(np.float64), u_H)
    fallback = (np.einsum("fnij,fnj->fni", frames, world) - ev.data.neutral_offset)[:, ev.uv_vertex]
    d1, d2, _ = ev.vertex_band.parameters(S, None if ev.validity is not None else ev.data.params.extrapolation_margin)
    if ev.validity is None:
        C = ev.medium_offsets(d1, d2)
    else:
        C = ev.medium_offsets(d1, d2, *ev.gauge(d1, d2), fallback.astype(np.float32))
    return pose.restore(X + np.einsum("fnji,fnj->fni", frames, C)), fallback


@pytest.fixture(scope="module")
def frames(pdm_model, pdm_data):
    """World markers of two training peaks and of the same motion 2.5× beyond them."""
    _, clips = pdm_data
    peak = clips[3].markers[[10, 12]]
    return np.concatenate([peak, beyond(pdm_model.evaluator, peak, 2.5)])


def test_the_fallback_on_the_kernels_is_the_float64_one(pdm_model, frames):
    ev = pdm_model.evaluator
    sm = ev.shell_mesh
    _, u_H, _ = ev.deformation(frames)
    _, ref = _float64_path(ev, frames)
    for k, u in enumerate(u_H):
        U, frames, Uc = sm.surface(u, correction=True)
        got = sm.fallback(Uc, frames)
        assert got.dtype == np.float32 and got.shape == ref[k].shape
        err = np.abs(got - ref[k]).max()
        assert err < FALLBACK_RTOL * np.abs(ref[k]).max(), err
        _, frames2, Uc2 = sm.surface(u, threads=2, correction=True)
        assert np.array_equal(sm.fallback(Uc2, frames2, threads=2), got)
        # the pair pass is each product alone, bit for bit
        assert np.array_equal(U, sm.frames.displacement(sm.basis, u))
        assert np.array_equal(Uc, sm.frames.displacement(sm.correction, u))
        assert sm.surface(u)[2] is None
    assert np.abs(ref).max() > 0.1                                      # a fallback the frames rotate


def test_synthesized_vertices_are_the_float64_mesh_on_any_kernel_threads(pdm_model, frames, monkeypatch):
    ev = pdm_model.evaluator
    want, _ = _float64_path(ev, frames)
    monkeypatch.setenv("NUMBA_NUM_THREADS", "1")
    got = pdm_model.synthesize(frames, outputs=("mesh",))["vertices"]
    err = np.abs(got - want).max()
    assert err < MESH_ATOL, err
    monkeypatch.setenv("NUMBA_NUM_THREADS", "2")
    assert np.array_equal(pdm_model.synthesize(frames, outputs=("mesh",))["vertices"], got)
    assert ev.validity is None or (ev.validity.gauge(*ev.vertex_band.parameters(
        ev.deformation(frames)[2], None)[:2]) > 1)[2:].mean() > 0.05     # the far frames use the fallback
