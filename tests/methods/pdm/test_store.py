"""Tests for service.methods.pdm.store: the model directory round trip and its integrity checks."""

import json

import numpy as np
import pytest

from service.io.exr import read_exr
from service.methods.pdm.model import PdmModel
from service.methods.model_dir import ModelCorrupt
from tests.methods.prior_modes import check_marker_modes
from tests.methods.verified import load_verified_without_hashing


@pytest.fixture(scope="module")
def saved(pdm_model, tmp_path_factory):
    path = tmp_path_factory.mktemp("pdm_store") / "model"
    return path, pdm_model.save(path)


def test_round_trip_is_bit_exact(pdm_model, pdm_data, saved):
    path, manifest = saved
    loaded = PdmModel.load(path)
    markers = pdm_data[1][4].markers[[0, 9, 15]]
    a = pdm_model.synthesize(markers, outputs=("mesh", "mesh_detailed", "displacement", "albedo"))
    b = loaded.synthesize(markers, outputs=("mesh", "mesh_detailed", "displacement", "albedo"))
    assert a.keys() == b.keys()
    for key in a:
        np.testing.assert_array_equal(a[key], b[key], err_msg=key)
    assert manifest["kind"] == "pdm" and manifest["metrics"]["pca_energy"] == pdm_model.metrics["pca_energy"]
    assert manifest["size_bytes"] == sum(p.stat().st_size for p in path.iterdir()
                                         if p.name not in ("manifest.json", "cache.npz"))
    assert manifest["derived_bytes"] == (path / "cache.npz").stat().st_size
    # the learned marker prior's modes, for a job's "auto" marker filter
    base = loaded.evaluator.base
    check_marker_modes(loaded.marker_modes, base.rest_markers, base.marker_prior, loaded.data.pose_weights)


def test_coefficient_maps_use_the_api_channel_names(saved):
    path, _ = saved
    medium, fine = read_exr(path / "medium.exr"), read_exr(path / "fine.exr")
    assert sorted(medium) == sorted(f"{c}.a{k}" for c in "xyz" for k in range(6))
    assert sorted(fine) == [f"n.a{k}" for k in range(6)]
    assert sorted(read_exr(path / "albedo.exr")) == sorted(f"{c}.a{k}" for c in "rgb" for k in range(6))
    assert medium["x.a0"].shape == (256, 256) and fine["n.a0"].shape == (128, 128)


def test_a_changed_or_missing_file_is_refused(saved, tmp_path):
    path, _ = saved
    import shutil

    broken = tmp_path / "broken"
    shutil.copytree(path, broken)
    data = bytearray((broken / "fine.exr").read_bytes())
    data[len(data) // 2] ^= 0x01
    (broken / "fine.exr").write_bytes(bytes(data))
    with pytest.raises(ModelCorrupt, match="fine.exr does not match its checksum"):
        PdmModel.load(broken)
    (broken / "fine.exr").unlink()
    with pytest.raises(ModelCorrupt, match="fine.exr is missing"):
        PdmModel.load(broken)
    manifest = json.loads((path / "manifest.json").read_text())
    manifest["format_version"] = 99
    (broken / "manifest.json").write_text(json.dumps(manifest))
    with pytest.raises(ModelCorrupt, match="not a pdm model of format 1"):
        PdmModel.load(broken)


def test_the_derived_cache_is_optional_and_changes_nothing(pdm_model, pdm_data, saved, tmp_path):
    import shutil

    path, _ = saved
    bare = tmp_path / "bare"
    shutil.copytree(path, bare)
    (bare / "cache.npz").unlink()
    manifest = json.loads((bare / "manifest.json").read_text())
    del manifest["derived"]
    (bare / "manifest.json").write_text(json.dumps(manifest))
    markers = pdm_data[1][2].markers[[5, 11]]
    a = pdm_model.synthesize(markers, outputs=("mesh", "displacement"))
    b = PdmModel.load(bare).synthesize(markers, outputs=("mesh", "displacement"))
    for key in a:
        np.testing.assert_array_equal(a[key], b[key], err_msg=key)


def test_the_validity_regions_are_stored_and_an_older_directory_derives_them(pdm_model, pdm_data, saved, tmp_path):
    import shutil

    path, manifest = saved
    assert "validity.npz" in manifest["files"]
    old = tmp_path / "old"                                  # as stored before validity.npz existed
    shutil.copytree(path, old)
    (old / "validity.npz").unlink()
    m = json.loads((old / "manifest.json").read_text())
    del m["files"]["validity.npz"]
    (old / "manifest.json").write_text(json.dumps(m))
    stored, derived = PdmModel.load(path), PdmModel.load(old)
    assert stored.data.validity is not None and derived.data.validity is None
    a, b = stored.evaluator.validity, derived.evaluator.validity
    assert np.array_equal(a.hull, b.hull) and a.envelope.keys() == b.envelope.keys() == {"vertex", "fine", "albedo"}
    for k in a.envelope:
        assert np.array_equal(a.envelope[k], b.envelope[k]), k
    markers = pdm_data[1][3].markers[[4, 12]]
    x = stored.synthesize(markers, outputs=("mesh", "displacement", "albedo"))
    y = derived.synthesize(markers, outputs=("mesh", "displacement", "albedo"))
    for key in x:
        np.testing.assert_array_equal(x[key], y[key], err_msg=key)
    # re-saved, the older model stores what its load derived: the next load reads it
    derived.save(tmp_path / "resaved")
    with np.load(path / "validity.npz") as want, np.load(tmp_path / "resaved" / "validity.npz") as got:
        assert set(got.files) == set(want.files) and "sector_box" in got.files
        for k in want.files:
            np.testing.assert_array_equal(got[k], want[k], err_msg=k)
    assert PdmModel.load(tmp_path / "resaved").data.validity.sector_box is not None


def test_the_coefficients_are_mapped_from_the_cache_and_equal_the_exr_decode(pdm_model, pdm_data, saved, tmp_path):
    """A load maps the maps' covered texels from cache.npz's stored .npy members (issue 23:
    no EXR decode, no file bytes held); a directory whose cache predates those members
    decodes the EXRs to the same arrays, bit for bit, and synthesizes the same frames."""
    import mmap
    import shutil

    from service.io.atomic import write_npz
    from service.io.npz import npz_arrays

    path, _ = saved
    older = tmp_path / "older"
    shutil.copytree(path, older)
    cache = npz_arrays((older / "cache.npz").read_bytes())
    assert {"medium_coeffs", "fine_coeffs", "albedo_coeffs", "fine_index"} <= cache.keys()
    m = json.loads((older / "manifest.json").read_text())
    m["derived"]["cache.npz"] = write_npz(older / "cache.npz", {
        k: v for k, v in cache.items() if not k.endswith(("_coeffs", "_index"))})
    (older / "manifest.json").write_text(json.dumps(m))
    mapped, decoded = PdmModel.load(path), PdmModel.load(older)
    for name in ("medium", "fine", "albedo"):
        a, b = getattr(mapped.data, name), getattr(decoded.data, name)
        np.testing.assert_array_equal(a.index, b.index)
        np.testing.assert_array_equal(a.coeffs, b.coeffs)
        assert a.coeffs.dtype == b.coeffs.dtype == np.float32
        base = a.coeffs
        while isinstance(base, np.ndarray) and base.base is not None:
            base = base.base
        assert isinstance(base, memoryview) and isinstance(base.obj, mmap.mmap)
        assert not a.coeffs.flags.writeable
    np.testing.assert_array_equal(mapped.data.S_train, pdm_model.data.S_train)
    markers = pdm_data[1][4].markers[[0, 9]]
    x = mapped.synthesize(markers, outputs=("mesh", "displacement", "normal_map", "albedo"))
    y = decoded.synthesize(markers, outputs=("mesh", "displacement", "normal_map", "albedo"))
    for key in x:
        np.testing.assert_array_equal(x[key], y[key], err_msg=key)


def test_a_loaded_model_leaves_the_medium_map_in_its_directory_and_saves_it_again(pdm_model, saved, tmp_path):
    """With vertex_coeffs the loaded model holds no medium-map arrays (issue 23: the model
    cache's estimate counted them mapped); saving the loaded model reads them from its
    directory, and the saved copy holds the trained coefficients bit for bit."""
    from service.methods.footprint import nbytes
    from service.methods.pdm.store import StoredCoefficientMap

    path, manifest = saved
    loaded = PdmModel.load(path)
    assert pdm_model.data.vertex_coeffs is not None
    medium = loaded.data.medium
    assert isinstance(medium, StoredCoefficientMap) and nbytes(medium) == 0
    trained = pdm_model.data.medium
    np.testing.assert_array_equal(medium.coeffs, trained.coeffs)
    np.testing.assert_array_equal(medium.index, trained.index)
    np.testing.assert_array_equal(medium.mask(), trained.mask())
    assert nbytes(loaded) < nbytes(pdm_model) - trained.coeffs.nbytes
    resaved = loaded.save(tmp_path / "again")
    assert resaved["files"]["medium.exr"] == manifest["files"]["medium.exr"]    # the same map, byte for byte
    again = PdmModel.load(tmp_path / "again")
    np.testing.assert_array_equal(again.data.medium.coeffs, trained.coeffs)


def test_the_evaluator_operators_are_stored_mapped_and_synthesize_bit_for_bit(pdm_model, pdm_data, saved, tmp_path):
    """Issue 23 (cold start): cache.npz holds the evaluator's operators (rasterization,
    parameter fields, element orders, sparse seam/sampling/validity matrices); a load maps
    them instead of deriving them, and synthesizes every output bit for bit as the trained
    model, as a directory whose cache predates them (which derives them), as operators
    of another version (derived anew), and as operators without the shell correction
    (derived alone)."""
    import dataclasses
    import shutil

    from service.io.atomic import write_npz
    from service.io.npz import npz_arrays
    from service.methods.footprint import file_mapped
    from service.methods.kinds import get_kind
    from service.methods.pdm import model as pdm
    from service.methods.pdm.store import read_model

    path, _ = saved
    cache = npz_arrays((path / "cache.npz").read_bytes())
    assert {"op_version", "op_fine_order", "op_fine_field_mono", "op_vertex_field_sorting_order",
            "op_fine_sampler_data", "op_seam_average_indptr", "op_fine_texel_rho_data",
            "op_albedo_texel_rho_data", "op_normal_mapper_texel", "op_normal_mapper_lam", "op_point_box",
            "op_shell_correction"} <= cache.keys()
    assert cache["op_normal_mapper_shape"].tolist() == [128, 128] and "op_raster_triangle" not in cache
    older = tmp_path / "older"
    shutil.copytree(path, older)
    m = json.loads((older / "manifest.json").read_text())
    m["derived"]["cache.npz"] = write_npz(older / "cache.npz", {
        k: v for k, v in cache.items() if not k.startswith("op_")})
    (older / "manifest.json").write_text(json.dumps(m))
    data, derived = read_model(path)
    other = dataclasses.replace(derived, operators={**derived.operators, "version": np.int64(pdm.OPERATORS_VERSION + 1)})
    no_shell = dataclasses.replace(derived, operators={k: v for k, v in derived.operators.items()
                                                       if k != "shell_correction"})    # this version, before it
    from service.geometry.uv_raster import rasterize_uv

    raster = rasterize_uv(data.uv, data.uv_faces, 128, 128)    # a cache stored before the mapper's arrays
    rasterized = dataclasses.replace(derived, operators={
        **{k: v for k, v in derived.operators.items() if not k.startswith("normal_mapper_")},
        "raster_triangle": raster.triangle.astype(np.int32), "raster_barycentric": raster.barycentric.astype(np.float32)})
    from_raster = PdmModel(data, pdm.PdmEvaluator.build(data, derived=rasterized))
    assert not file_mapped(from_raster.evaluator.normal_mapper.texels)
    mapped, built = PdmModel.load(path), PdmModel.load(older)
    rebuilt = PdmModel(data, pdm.PdmEvaluator.build(data, derived=other))
    shell = PdmModel(data, pdm.PdmEvaluator.build(data, derived=no_shell))
    assert file_mapped(mapped.evaluator.shell_correction) and not file_mapped(shell.evaluator.shell_correction)
    np.testing.assert_array_equal(shell.evaluator.shell_correction, mapped.evaluator.shell_correction)
    ev = mapped.evaluator
    assert file_mapped(ev.fine.field.mono) and file_mapped(ev.fine_sampler.data) and file_mapped(ev.seam_average.indices)
    assert file_mapped(ev.validity.texel_rho["fine"].data) and not file_mapped(ev.fine.field.element)
    assert not file_mapped(ev.orders["fine"])          # read at load only: into memory, not mapped
    assert file_mapped(ev.normal_mapper.texels)          # issue 23: mapped, not built
    assert file_mapped(ev.point_validity.box) and ev.point_validity.box.shape[2:] == (2, 3)   # the kernel's layout
    assert not file_mapped(built.evaluator.point_validity.box)                                # transposed at load
    np.testing.assert_array_equal(built.evaluator.point_validity.box, ev.point_validity.box)
    for model in (built, rebuilt):
        assert not file_mapped(model.evaluator.fine.field.mono)
        np.testing.assert_array_equal(model.evaluator.orders["fine"], ev.orders["fine"])
    markers = pdm_data[1][4].markers[[0, 9, 15]]
    outputs = get_kind("pdm").outputs
    a = pdm_model.synthesize(markers, outputs=outputs)
    assert {"vertices", "vertices_detailed", "normal_map", "albedo", "displacement"} <= a.keys()
    for model in (mapped, built, rebuilt, shell, from_raster):
        b = model.synthesize(markers, outputs=outputs)
        assert a.keys() == b.keys()
        for key in a:
            np.testing.assert_array_equal(a[key], b[key], err_msg=key)


def test_the_shell_mesh_bases_are_stored_in_its_order_and_mapped(pdm_model, pdm_data, saved):
    """Issue 23: the compiled mesh's two thin-shell bases in its vertex order are in the cache
    (``op_shell_mesh_*``) and a load maps them instead of permuting (n,M) twice; a cache
    without them (this operators version, before) or with another vertex order permutes
    the bases again; every load synthesizes the mesh bit for bit as the trained model."""
    import dataclasses

    from service.methods.footprint import file_mapped
    from service.methods.pdm import model as pdm
    from service.methods.pdm.store import read_model

    path, _ = saved
    data, derived = read_model(path)
    ops = derived.operators
    sm = pdm_model.evaluator.shell_mesh
    np.testing.assert_array_equal(ops["shell_mesh_order"], sm.order)
    np.testing.assert_array_equal(ops["shell_mesh_basis"], sm.basis)
    np.testing.assert_array_equal(ops["shell_mesh_correction"], sm.correction)
    mapped = PdmModel.load(path)
    assert file_mapped(mapped.evaluator.shell_mesh.basis) and file_mapped(mapped.evaluator.shell_mesh.correction)
    for k, v in sm.frames.arrays().items():                # the ShellFrames too: mapped, not built
        np.testing.assert_array_equal(ops[f"shell_mesh_frames_{k}"], v)
        assert file_mapped(getattr(mapped.evaluator.shell_mesh.frames, k)) == (k != "order"), k  # *_order: read
    without = {k: v for k, v in ops.items() if not k.startswith("shell_mesh_")}
    other = {**ops, "shell_mesh_order": np.ascontiguousarray(ops["shell_mesh_order"][::-1])}
    markers = pdm_data[1][4].markers[[0, 9, 15]]
    want = pdm_model.synthesize(markers, outputs=("mesh",))["vertices"]
    assert np.array_equal(mapped.synthesize(markers, outputs=("mesh",))["vertices"], want)
    for operators in (without, other):
        model = PdmModel(data, pdm.PdmEvaluator.build(data, derived=dataclasses.replace(derived, operators=operators)))
        sm2 = model.evaluator.shell_mesh
        assert not file_mapped(sm2.basis) and not file_mapped(sm2.correction)
        np.testing.assert_array_equal(sm2.basis, sm.basis)
        for k, v in sm.frames.arrays().items():
            np.testing.assert_array_equal(getattr(sm2.frames, k), v)
        assert np.array_equal(model.synthesize(markers, outputs=("mesh",))["vertices"], want)


def test_the_marker_prior_is_stored_and_an_older_directory_loads_without_it(pdm_model, pdm_data, saved, tmp_path):
    """Training learns the marker prior (issue 17) and the store round-trips it; a directory
    saved before it existed (no ``marker_prior_*`` arrays) loads with none and synthesizes
    the same at σ = 0 (its params' default; with σ > 0 it would use the shell prior alone,
    tests/methods/pdm/test_base_surface.py), except that its confidence has no noise factor
    (no prior to estimate σ̂ with: service.methods.confidence)."""
    import shutil

    from service.io.atomic import write_npz

    path, _ = saved
    prior = pdm_model.data.marker_prior
    assert prior is not None and prior.covariance.shape == (3 * pdm_model.data.n_markers,) * 2
    loaded = PdmModel.load(path)
    np.testing.assert_array_equal(loaded.data.marker_prior.covariance, prior.covariance)
    np.testing.assert_array_equal(loaded.data.marker_prior.mean, prior.mean)
    old = tmp_path / "old"
    shutil.copytree(path, old)
    with np.load(old / "model.npz") as a:
        arrays = {k: a[k] for k in a.files if not k.startswith("marker_prior_") or k == "marker_prior_scale_mm"}
    m = json.loads((old / "manifest.json").read_text())
    m["files"]["model.npz"] = write_npz(old / "model.npz", arrays)
    m["size_bytes"] = sum((old / f).stat().st_size for f in m["files"])
    (old / "manifest.json").write_text(json.dumps(m))
    before = PdmModel.load(old)
    assert before.data.marker_prior is None and before.evaluator.base.denoiser is None
    markers = pdm_data[1][2].markers[[3, 11]]
    x, y = loaded.synthesize(markers, outputs=("mesh",)), before.synthesize(markers, outputs=("mesh",))
    assert x.keys() == y.keys() and "vertices" in x
    pose, u_H, _ = loaded.evaluator.deformation(markers)
    factor = loaded.evaluator.base.input_confidence(pose.remove(markers), u_H)
    assert before.evaluator.base.evidence is None and np.all(factor < 1)
    for key in x:
        if key in ("confidence", "confidence_vertices"):
            np.testing.assert_allclose(y[key] * factor.reshape(-1, *[1] * (y[key].ndim - 1)), x[key], rtol=1e-6)
        else:
            np.testing.assert_array_equal(y[key], x[key], err_msg=key)


def test_a_directory_the_blob_store_verified_is_not_hashed_again(pdm_model, pdm_data, saved, monkeypatch):
    path, _ = saved
    loaded = load_verified_without_hashing(PdmModel.load, path, monkeypatch)
    markers = pdm_data[1][4].markers[[0, 9]]
    np.testing.assert_array_equal(loaded.synthesize(markers, outputs=("mesh",))["vertices"],
                                  pdm_model.synthesize(markers, outputs=("mesh",))["vertices"])


def test_the_band_terms_and_frame_field_are_stored_mapped_and_synthesize_bit_for_bit(pdm_model, pdm_data, saved):
    """Issue 23 (cold start): the fine and albedo bands' term-major coefficients
    (``op_<band>_terms``) and the base surface's FrameField operators (``op_frame_field_*``)
    are in the cache; a load maps them instead of copying the coefficients and building the
    field; a cache of this operators version without them (saved before) does both as
    before; every output synthesizes bit for bit as the trained model either way."""
    import dataclasses

    from service.geometry.tangent_frames import OPERATORS
    from service.methods.footprint import file_mapped
    from service.methods.kinds import get_kind
    from service.methods.pdm import model as pdm
    from service.methods.pdm.store import read_model

    path, _ = saved
    data, derived = read_model(path)
    ops = derived.operators
    ev0 = pdm_model.evaluator
    for name in ("fine", "albedo"):
        np.testing.assert_array_equal(ops[f"{name}_terms"], getattr(ev0, name).terms)
    for k in OPERATORS:
        m = getattr(ev0.base.frame_field, k)
        for part in ("data", "indices", "indptr"):
            np.testing.assert_array_equal(ops[f"frame_field_{k}_{part}"], getattr(m, part))
    mapped = PdmModel.load(path)
    ev = mapped.evaluator
    assert file_mapped(ev.fine.terms) and file_mapped(ev.albedo.terms) and np.shares_memory(ev.fine.coeffs, ev.fine.terms)
    assert all(file_mapped(getattr(ev.base.frame_field, k).data) for k in OPERATORS)
    without = {k: v for k, v in ops.items() if not (k.startswith("frame_field_") or k.endswith("_terms"))}
    built = PdmModel(data, pdm.PdmEvaluator.build(data, derived=dataclasses.replace(derived, operators=without)))
    assert not file_mapped(built.evaluator.fine.terms)
    assert not any(file_mapped(getattr(built.evaluator.base.frame_field, k).data) for k in OPERATORS)
    markers = pdm_data[1][4].markers[[0, 9, 15]]
    outputs = get_kind("pdm").outputs
    a = pdm_model.synthesize(markers, outputs=outputs)
    for model in (mapped, built):
        b = model.synthesize(markers, outputs=outputs)
        for key in a:
            np.testing.assert_array_equal(a[key], b[key], err_msg=key)


def test_the_fit_skill_is_stored_and_an_older_directory_loads_without_it(pdm_model, pdm_data, saved, tmp_path):
    """Training measures the medium band's cross-validated skill at every UV point (issue 17,
    service.methods.pdm.fit_skill) and the store round-trips it; ``fit_skill_floor`` null (the
    default) applies no gain; a directory saved before the skill existed loads with none and
    synthesizes bit for bit the same; the floor turns the gain on (skill_gain of the stored skill)."""
    import dataclasses
    import shutil

    from service.io.atomic import write_npz
    from service.methods.pdm.fit_skill import skill_gain

    path, _ = saved
    skill = pdm_model.data.medium_skill
    assert skill.shape == (len(pdm_model.data.uv),) and skill.dtype == np.float32 and np.all(skill <= 1)
    assert pdm_model.evaluator.medium_gain is None
    loaded = PdmModel.load(path)
    np.testing.assert_array_equal(loaded.data.medium_skill, skill)
    old = tmp_path / "old"
    shutil.copytree(path, old)
    with np.load(old / "model.npz") as a:
        arrays = {k: a[k] for k in a.files if k != "medium_skill"}
    m = json.loads((old / "manifest.json").read_text())
    m["files"]["model.npz"] = write_npz(old / "model.npz", arrays)
    m["size_bytes"] = sum((old / f).stat().st_size for f in m["files"])
    (old / "manifest.json").write_text(json.dumps(m))
    before = PdmModel.load(old)
    assert before.data.medium_skill is None and before.evaluator.medium_gain is None
    markers = pdm_data[1][2].markers[[3, 11]]
    np.testing.assert_array_equal(before.synthesize(markers, outputs=("mesh",))["vertices"],
                                  loaded.synthesize(markers, outputs=("mesh",))["vertices"])
    data = dataclasses.replace(loaded.data, params=loaded.params.model_copy(update={"fit_skill_floor": 0.0}))
    gained = PdmModel(data)
    np.testing.assert_array_equal(gained.evaluator.medium_gain, skill_gain(skill, 0.0))
    assert not np.array_equal(gained.synthesize(markers, outputs=("mesh",))["vertices"],
                              loaded.synthesize(markers, outputs=("mesh",))["vertices"])
