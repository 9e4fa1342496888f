"""Tests for service.methods.model_dir: a directory the blob store verified is hashed once."""

import hashlib
import json

import pytest

from models_store.blobs import BlobStore, VerifiedDir, VerifyingDir
from service.methods import model_dir
from service.methods.model_dir import ModelCorrupt, read_model_files


@pytest.fixture
def stored(tmp_path):
    """A two-file model directory of kind ``toy`` put into a blob store."""
    src = tmp_path / "src"
    src.mkdir()
    files = {"a.npz": b"\x01" * 3000, "b.exr": b"\x02" * 700}
    for name, data in files.items():
        (src / name).write_bytes(data)
    manifest = {"kind": "toy", "format_version": 1,
                "files": {n: hashlib.sha256(d).hexdigest() for n, d in files.items()}}
    (src / "manifest.json").write_text(json.dumps(manifest))
    blobs = BlobStore(tmp_path / "blobs")
    return blobs, blobs.put_dir("models/m/v1", src), files


def test_a_verified_directory_is_not_hashed_again(stored, monkeypatch):
    blobs, info, files = stored
    path = blobs.open_dir(info.key, info.sha256)
    assert isinstance(path, VerifiedDir) and sorted(path.digests) == ["a.npz", "b.exr", "manifest.json"]
    assert path.digests["a.npz"] == hashlib.sha256(files["a.npz"]).hexdigest()

    def no_hashing(*args):
        raise AssertionError("hashed a second time")

    monkeypatch.setattr(model_dir, "sha256_file", no_hashing)
    monkeypatch.setattr(model_dir.hashlib, "sha256", no_hashing)
    manifest, data = read_model_files(path, "toy", 1, mapped=lambda name: name == "a.npz")
    assert data["a.npz"] == path / "a.npz" and data["b.exr"] == files["b.exr"]


def test_a_verified_digest_that_differs_from_the_manifest_is_refused(stored):
    blobs, info, _ = stored
    path = blobs.open_dir(info.key, info.sha256)
    wrong = VerifiedDir.of(path, {**path.digests, "b.exr": "0" * 64})
    with pytest.raises(ModelCorrupt, match="b.exr does not match its checksum"):
        read_model_files(wrong, "toy", 1)
    missing = VerifiedDir.of(path, {k: v for k, v in path.digests.items() if k != "a.npz"})
    with pytest.raises(ModelCorrupt, match="a.npz is missing"):
        read_model_files(missing, "toy", 1, mapped=lambda name: True)


def test_a_directory_being_verified_is_compared_at_confirm(stored, monkeypatch):
    blobs, info, files = stored
    path = blobs.open_dir(info.key, info.sha256, background=True)
    manifest, data = read_model_files(path, "toy", 1, mapped=lambda name: name == "a.npz")
    assert data["b.exr"] == files["b.exr"]
    path.confirm()
    # a manifest that disagrees with the verified files fails at confirm, not at the read
    (blobs.root.parent / "alt").mkdir()
    for name in files:
        (blobs.root.parent / "alt" / name).write_bytes(files[name])
    listed = {**manifest["files"], "b.exr": "0" * 64}
    (blobs.root.parent / "alt" / "manifest.json").write_text(json.dumps({**manifest, "files": listed}))
    alt = blobs.put_dir("models/m/v2", blobs.root.parent / "alt")
    pending = blobs.open_dir(alt.key, alt.sha256, background=True)
    assert isinstance(pending, VerifyingDir)
    read_model_files(pending, "toy", 1)
    with pytest.raises(ModelCorrupt, match="b.exr does not match its checksum"):
        pending.confirm()
