"""The per-request lookups of ``/synthesize`` (issue 23): a ready model's row read once per
``READY_RECHECK_SECONDS`` while it stays cached, the tenant checked on every request, a
deletion in this process answered 404 at once and one by another process within that time;
the half-precision response the same bytes as before the vectorized float16 conversion."""

from __future__ import annotations

import io
import zipfile

import numpy as np
import pytest

from models_store import registry
from models_store.registry import acting_for
from service.app import services as services_module
from service.app.services import READY_RECHECK_SECONDS, Services
from service.config import Settings
from service.errors import NotFound
from tests.api.conftest import NPZ, Recorder, assert_problem, make_client, npz, upload_sample_actor
from tests.conftest import PDM_TRAINING


@pytest.fixture(scope="module")
def models(tmp_path_factory, pdm_actor_dir, pdm_model):
    """(client, settings, [model_id] * 3, heldout markers (2,M,3)): three ready copies of the
    session's PDM for one uploaded sample actor (two are deleted below)."""
    tmp = tmp_path_factory.mktemp("api_lookups")
    settings = Settings(data_dir=tmp / "data", max_frames_per_request=4)
    with make_client(settings, Recorder()) as client:
        actor_id, clip_ids = upload_sample_actor(client, pdm_actor_dir, PDM_TRAINING[:1])
        clip = clip_ids[PDM_TRAINING[0]]
        pdm_model.save(tmp / "model")
        services = client.app.state.services
        ids = []
        for _ in range(3):
            model_id = client.post(f"/v1/actors/{actor_id}/models", json={
                "kind": "pdm", "clips": [clip]}).json()["model_id"]
            with services.session() as session:
                registry.mark_model_ready(session, services.blobs, model_id, tmp / "model",
                                          metrics=pdm_model.metrics)
            ids.append(model_id)
        with np.load(pdm_actor_dir / "performances" / "heldout_in_range.npz") as d:
            heldout = d["markers"][:2].astype(np.float64)
        yield client, settings, ids, heldout


def synth(client, model_id, markers, **params):
    return client.post(f"/v1/models/{model_id}/synthesize", content=npz(markers=markers),
                       headers=NPZ, params={"outputs": "mesh", **params})


class Clock:
    """``time.monotonic`` of the services module, moved by hand."""

    def __init__(self, monkeypatch):
        self.now = 1000.0
        monkeypatch.setattr(services_module.time, "monotonic", lambda: self.now)


def count_reads(monkeypatch) -> list[str]:
    reads: list[str] = []
    get_model = registry.get_model

    def counted(session, model_id, *args, **kwargs):
        reads.append(model_id)
        return get_model(session, model_id, *args, **kwargs)

    monkeypatch.setattr(services_module.registry, "get_model", counted)
    return reads


def test_the_row_is_read_once_per_recheck_interval_and_the_tenant_on_every_request(
        models, monkeypatch):
    client, _, (model_id, _, _), markers = models
    services = client.app.state.services
    assert synth(client, model_id, markers[:1]).status_code == 200     # loaded and cached
    clock = Clock(monkeypatch)
    reads = count_reads(monkeypatch)
    services.ready_rows.clear()
    for _ in range(3):
        assert synth(client, model_id, markers[:1]).status_code == 200
    assert reads == [model_id]                                          # one read, not three
    clock.now += READY_RECHECK_SECONDS + 0.01
    assert synth(client, model_id, markers[:1]).status_code == 200
    assert reads == [model_id, model_id]                                # read again after it
    # another tenant: the NotFound of an unknown id, from the remembered row as from a read
    unknown = "mdl_" + "0" * 26
    with acting_for("studio-b", "studio-b"):
        with pytest.raises(NotFound) as crossed:
            services.loaded_model(model_id)
        with pytest.raises(NotFound) as twin:
            services.loaded_model(unknown)
    assert str(crossed.value).replace(model_id, unknown) == str(twin.value)
    assert len(reads) == 3                                              # the unknown one only
    with acting_for("default", "default"):
        assert services.loaded_model(model_id).id == model_id
    services.ready_rows.clear()
    with acting_for("studio-b", "studio-b"), pytest.raises(NotFound):
        services.loaded_model(model_id)                                 # as read from the row


def test_a_deleted_model_answers_404_at_once_here_and_within_the_interval_elsewhere(
        models, monkeypatch):
    client, settings, (kept, deleted, _), markers = models
    for model_id in (kept, deleted):
        assert synth(client, model_id, markers[:1]).status_code == 200
    assert client.delete(f"/v1/models/{deleted}").status_code == 204
    assert_problem(synth(client, deleted, markers[:1]), 404, deleted)   # at once, no wait
    # deleted by another process (its own Services on the same store): served from this
    # process's cache for at most READY_RECHECK_SECONDS, then 404
    clock = Clock(monkeypatch)
    services = client.app.state.services
    services.ready_rows.clear()
    assert synth(client, kept, markers[:1]).status_code == 200          # row read at `now`
    other = Services.open(settings)
    try:
        with other.session() as session:
            registry.delete_model(session, other.blobs, kept)
    finally:
        other.close()
    clock.now += 0.5 * READY_RECHECK_SECONDS
    assert synth(client, kept, markers[:1]).status_code == 200
    clock.now += 0.5 * READY_RECHECK_SECONDS + 0.01
    assert_problem(synth(client, kept, markers[:1]), 404, kept)
    assert kept in services.models                     # the bytes stay until evicted, unused


def test_a_deletion_during_a_row_read_is_not_remembered(models):
    """A request that read the row before a deletion in this process does not leave it
    remembered after the deletion (the next request reads the row again)."""
    client, _, _, _ = models
    services = client.app.state.services
    seen = services.forgotten
    services.forget_model("mdl_" + "1" * 26)
    assert services.forgotten == seen + 1 and "mdl_" + "1" * 26 not in services.ready_rows


def test_half_response_is_byte_identical_to_numpy_astype(models, pdm_model):
    """Every zip member of a ``half=true`` response (npy header and data) is byte for byte
    what the float32 response's arrays give through NumPy's own astype(float16) and
    np.savez, in the same order (only the zip's timestamps may differ)."""
    from service.methods.outputs import MAP_OUTPUTS

    client, _, (_, _, model_id), markers = models
    outputs = "mesh,displacement,normal_map"
    full = synth(client, model_id, markers, outputs=outputs, topology="false")
    half = synth(client, model_id, markers, outputs=outputs, topology="false", half="true")
    arrays = dict(np.load(io.BytesIO(full.content)))
    for name in MAP_OUTPUTS:
        if name in arrays:
            arrays[name] = arrays[name].astype(np.float16)
    before = io.BytesIO()
    np.savez(before, **arrays)
    with zipfile.ZipFile(io.BytesIO(half.content)) as got, zipfile.ZipFile(before) as want:
        assert got.namelist() == want.namelist()
        for name in want.namelist():
            assert got.read(name) == want.read(name), name
