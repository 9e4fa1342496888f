"""models_store.registry.scans on SQLite and PostgreSQL: scans stored under the actor's
prefix, owned by one actor, deleted with their blob and with the actor."""

from __future__ import annotations

import pytest

from models_store import registry as reg
from models_store.errors import BlobCorrupt, NotFound


@pytest.fixture
def actor(session):
    return reg.create_actor(session, "Ada")


def test_add_list_read_and_delete(session, blobs, actor):
    first = reg.add_scan(session, blobs, actor.id, b"npz-1", width=64, height=32,
                         maps=["position", "albedo"], name="neutral")
    second = reg.add_scan(session, blobs, actor.id, b"npz-22", width=8, height=8, maps=["albedo"])
    assert first.id.startswith("scn_") and first.blob.startswith(f"actors/{actor.id}/scans/")
    assert (first.width, first.height, first.maps, first.size_bytes) == (64, 32, ["albedo", "position"], 5)
    assert [s.id for s in reg.list_scans(session, actor.id)] == [first.id, second.id]
    assert reg.read_scan(session, blobs, first.id) == b"npz-1"
    reg.delete_scan(session, blobs, first.id, actor.id)
    assert [s.id for s in reg.list_scans(session, actor.id)] == [second.id]
    assert not blobs.exists(first.blob)
    with pytest.raises(NotFound):
        reg.get_scan(session, first.id)


def test_scans_belong_to_one_actor(session, blobs, actor):
    other = reg.create_actor(session, "Bo")
    scan = reg.add_scan(session, blobs, actor.id, b"x", width=8, height=8, maps=["albedo"])
    with pytest.raises(NotFound, match="another actor"):
        reg.get_scan(session, scan.id, other.id)
    with pytest.raises(NotFound, match="another actor"):
        reg.delete_scan(session, blobs, scan.id, other.id)
    with pytest.raises(NotFound):
        reg.add_scan(session, blobs, "act_00000000000000000000000000", b"x", width=8, height=8,
                     maps=["albedo"])
    with pytest.raises(ValueError):
        reg.add_scan(session, blobs, actor.id, b"x", width=0, height=8, maps=["albedo"])


def test_a_corrupt_scan_blob_is_detected(session, blobs, actor):
    scan = reg.add_scan(session, blobs, actor.id, b"original", width=8, height=8, maps=["albedo"])
    blobs.path(scan.blob).write_bytes(b"tampered")
    with pytest.raises(BlobCorrupt):
        reg.read_scan(session, blobs, scan.id)


def test_deleting_the_actor_deletes_its_scans(session, blobs, actor):
    scan = reg.add_scan(session, blobs, actor.id, b"x", width=8, height=8, maps=["albedo"])
    reg.delete_actor(session, blobs, actor.id)
    assert not blobs.exists(scan.blob)
    with pytest.raises(NotFound):
        reg.get_scan(session, scan.id)
