"""BlobStore: bit-exact round trips, checksums, atomic write-once puts, safe keys, modes."""

from __future__ import annotations

import hashlib
import os
import stat

import numpy as np
import pytest

from models_store.blobs import CHUNK, BlobStore, VerifyingDir, tree_digest, validate_key
from models_store.errors import BlobCorrupt, Conflict, InvalidId, NotFound


def random_bytes(n: int, seed: int = 0) -> bytes:
    return np.random.default_rng(seed).integers(0, 256, n, dtype=np.uint8).tobytes()


@pytest.fixture
def model_dir(tmp_path):
    """A small model-like directory tree."""
    root = tmp_path / "model"
    (root / "maps").mkdir(parents=True)
    (root / "manifest.json").write_text('{"kind": "pdm"}')
    (root / "arrays.npz").write_bytes(random_bytes(3 * CHUNK + 17, seed=1))
    (root / "maps" / "x.exr").write_bytes(random_bytes(1000, seed=2))
    (root / "empty").write_bytes(b"")
    return root


def files_of(root):
    return {p.relative_to(root).as_posix(): p.read_bytes()
            for p in sorted(root.rglob("*")) if p.is_file()}


def leftovers(root):
    """Temporary names left anywhere in the store."""
    return [p for p in root.rglob(".*")]


def test_put_bytes_round_trip_is_bit_exact(blobs):
    data = bytes(range(256)) * 7 + random_bytes(2 * CHUNK + 5)   # every byte value, > 1 chunk
    info = blobs.put_bytes("actors/act_x/clip", data)
    assert info.sha256 == hashlib.sha256(data).hexdigest()
    assert info.size == len(data)
    assert blobs.read_bytes(info.key, info.sha256) == data
    with blobs.open(info.key, info.sha256) as f:
        assert f.read() == data
    assert leftovers(blobs.root) == []


def test_put_file_copies_the_file_exactly(blobs, tmp_path):
    source = tmp_path / "neutral.npz"
    source.write_bytes(random_bytes(12345))
    info = blobs.put_file("neutral", source)
    assert blobs.read_bytes("neutral", info.sha256) == source.read_bytes()
    assert info.size == 12345


def test_put_dir_round_trip_and_tree_digest(blobs, model_dir):
    info = blobs.put_dir("models/mdl_x/v1", model_dir)
    stored = blobs.open_dir(info.key, info.sha256)
    assert files_of(stored) == files_of(model_dir)
    assert info.size == sum(len(b) for b in files_of(model_dir).values())
    # the digest is sha256 over `sha256sum`-style lines sorted by path
    lines = "".join(f"{hashlib.sha256(b).hexdigest()}  {p}\n"
                    for p, b in sorted(files_of(model_dir).items()))
    assert info.sha256 == hashlib.sha256(lines.encode()).hexdigest()
    assert leftovers(blobs.root) == []


def test_corrupted_file_raises_blob_corrupt(blobs):
    info = blobs.put_bytes("a/b", random_bytes(5000))
    path = blobs.path("a/b")
    data = bytearray(path.read_bytes())
    data[2500] ^= 0x01                       # one flipped bit
    path.write_bytes(bytes(data))
    with pytest.raises(BlobCorrupt, match="'a/b' is corrupt") as caught:
        blobs.read_bytes("a/b", info.sha256)
    assert caught.value.expected == info.sha256
    with pytest.raises(BlobCorrupt):
        blobs.open("a/b", info.sha256)


@pytest.mark.parametrize("damage", ["flip", "extra_file", "missing_file", "rename"])
def test_corrupted_directory_raises_blob_corrupt(blobs, model_dir, damage):
    info = blobs.put_dir("m", model_dir)
    stored = blobs.path("m")
    if damage == "flip":
        target = stored / "maps" / "x.exr"
        data = bytearray(target.read_bytes())
        data[0] ^= 0x80
        target.write_bytes(bytes(data))
    elif damage == "extra_file":
        (stored / "maps" / "y.exr").write_bytes(b"")
    elif damage == "missing_file":
        (stored / "empty").unlink()
    else:
        (stored / "empty").rename(stored / "empty2")
    with pytest.raises(BlobCorrupt):
        blobs.open_dir("m", info.sha256)


@pytest.mark.parametrize("damage", ["none", "flip", "missing_file"])
def test_a_directory_verified_in_the_background_fails_only_at_confirm(blobs, model_dir, damage):
    info = blobs.put_dir("m", model_dir)
    stored = blobs.path("m")
    if damage == "flip":
        target = stored / "maps" / "x.exr"
        data = bytearray(target.read_bytes())
        data[0] ^= 0x80
        target.write_bytes(bytes(data))
    elif damage == "missing_file":
        (stored / "empty").unlink()
    pending = blobs.open_dir("m", info.sha256, background=True)
    assert isinstance(pending, VerifyingDir) and pending == stored
    seen = []
    pending.after_verify(seen.append)
    if damage == "none":
        pending.confirm()
        assert seen == [blobs.open_dir("m", info.sha256).digests] == [pending.digests]
        return
    with pytest.raises(BlobCorrupt, match="'m' is corrupt"):
        pending.confirm()
    assert seen == []   # no deferred check runs on files that failed


@pytest.mark.parametrize("key", [
    "../outside", "a/../../outside", "/etc/passwd", "a//b", "a/", ".hidden", "a/.x.tmp",
    "a\\..\\b", "a b", "", "x" * 129, "a/\n", None,
])
def test_keys_with_traversal_or_odd_characters_are_rejected(blobs, key):
    with pytest.raises(InvalidId, match="blob key"):
        validate_key(key)
    with pytest.raises(InvalidId):
        blobs.put_bytes(key, b"data")
    assert not (blobs.root.parent / "outside").exists()


def test_blobs_are_write_once(blobs, model_dir):
    first = blobs.put_bytes("k", b"one")
    with pytest.raises(Conflict, match="'k' is already taken"):
        blobs.put_bytes("k", b"two")
    assert blobs.read_bytes("k", first.sha256) == b"one"
    blobs.put_dir("d", model_dir)
    with pytest.raises(Conflict):
        blobs.put_dir("d", model_dir)
    assert leftovers(blobs.root) == []


def test_blobs_are_readable_by_other_users_whatever_the_umask(blobs, model_dir):
    old = os.umask(0o077)
    try:
        blobs.put_bytes("deep/er/file", b"x")
        blobs.put_dir("deep/model", model_dir)
    finally:
        os.umask(old)
    modes = {p.relative_to(blobs.root).as_posix(): stat.S_IMODE(p.stat().st_mode)
             for p in blobs.root.rglob("*")}
    assert modes["deep"] == modes["deep/er"] == modes["deep/model/maps"] == 0o755
    assert modes["deep/model"] == 0o755
    assert modes["deep/er/file"] == modes["deep/model/maps/x.exr"] == 0o644
    assert set(modes.values()) == {0o755, 0o644}


def test_failed_put_dir_leaves_nothing_behind(blobs, model_dir):
    (model_dir / "link").symlink_to(model_dir / "manifest.json")
    with pytest.raises(ValueError, match="symbolic link"):
        blobs.put_dir("m", model_dir)
    assert not blobs.exists("m")
    assert leftovers(blobs.root) == []


def test_put_dir_of_a_file_is_refused(blobs, tmp_path):
    (tmp_path / "f").write_bytes(b"")
    with pytest.raises(ValueError, match="not a directory"):
        blobs.put_dir("m", tmp_path / "f")


def test_delete_removes_files_directories_and_prefixes(blobs, model_dir):
    blobs.put_bytes("actors/a/neutral", b"n")
    blobs.put_bytes("actors/a/clips/c1", b"c")
    blobs.put_dir("models/m/v1", model_dir)
    assert blobs.delete("models/m/v1")
    assert not blobs.path("models/m/v1").exists()
    assert blobs.delete("actors/a")                   # a whole prefix
    assert not blobs.path("actors/a").exists()
    assert not blobs.delete("actors/a")               # already gone
    assert leftovers(blobs.root) == []


def test_missing_blobs_raise_not_found(blobs):
    with pytest.raises(NotFound, match="'nothing' not found"):
        blobs.read_bytes("nothing", "0" * 64)
    with pytest.raises(NotFound):
        blobs.open_dir("nothing", "0" * 64)
    with pytest.raises(NotFound):
        blobs.digest("nothing")


def test_a_second_store_on_the_same_root_sees_the_blobs(blobs):
    info = blobs.put_bytes("shared", b"payload")
    other = BlobStore(blobs.root)
    assert other.read_bytes("shared", info.sha256) == b"payload"


def test_tree_digest_depends_on_paths_and_contents():
    a = tree_digest({"x": "1" * 64, "y": "2" * 64})
    assert a == tree_digest({"y": "2" * 64, "x": "1" * 64})     # order-independent
    assert a != tree_digest({"x": "2" * 64, "y": "1" * 64})
    assert a != tree_digest({"x": "1" * 64, "z": "2" * 64})


# -- temporaries left by crashes (issue 16, defect 3) and the readiness probe (defect 4) ----
SCRATCH_CHILD = r"""
import os, sys, time
from models_store.blobs import BlobStore
with BlobStore(sys.argv[1]).scratch_dir("synthesize") as path:
    (path / "vertices.npy").write_bytes(b"x" * 1000)
    print(path.name, flush=True)
    time.sleep(60)                          # killed here
"""


def _age(path, seconds):
    """Set the modification time of ``path`` and everything under it ``seconds`` back."""
    import time

    then = time.time() - seconds
    for p in [path, *path.rglob("*")] if path.is_dir() else [path]:
        os.utime(p, (then, then))


def test_sweep_removes_old_temporaries_and_keeps_blobs_young_ones_and_live_scratch(blobs):
    import subprocess
    import sys

    blobs.put_bytes("actors/a/clips/clp_1", b"clip")
    leftover_file = blobs.root / "actors" / "a" / "clips" / ".clp_2.k3j4.tmp"
    leftover_file.write_bytes(b"half a clip")
    leftover_dir = blobs.root / "models" / "m" / ".01j9.abc.tmp"
    (leftover_dir / "maps").mkdir(parents=True)
    (leftover_dir / "maps" / "x.exr").write_bytes(b"half a model")
    young = blobs.root / "actors" / "a" / ".neutral-x.y.tmp"
    young.write_bytes(b"being written")
    # a worker SIGKILLed in the middle of a synthesis leaves its scratch directory
    child = subprocess.Popen([sys.executable, "-c", SCRATCH_CHILD, str(blobs.root)],
                             stdout=subprocess.PIPE, text=True)
    killed = blobs.root / child.stdout.readline().strip()
    child.kill()
    child.wait(10)
    assert killed.is_dir() and killed.name.startswith(".synthesize-")
    with blobs.scratch_dir("train") as live:
        (live / "model.npz").write_bytes(b"in use")
        for path in (leftover_file, leftover_dir, killed, live):
            _age(path, 3600)
        removed = blobs.sweep_temporaries(older_than=600)
        assert sorted(removed) == sorted(["actors/a/clips/.clp_2.k3j4.tmp",
                                          "models/m/.01j9.abc.tmp", killed.name])
        assert live.is_dir() and (live / "model.npz").read_bytes() == b"in use"
    assert not live.exists()                       # the block's end removed it
    assert young.exists() and blobs.read_bytes("actors/a/clips/clp_1",
                                               hashlib.sha256(b"clip").hexdigest()) == b"clip"
    assert blobs.sweep_temporaries(older_than=600) == []


def test_scratch_prefix_is_checked(blobs):
    with pytest.raises(ValueError, match="scratch prefix"):
        with blobs.scratch_dir("../x"):
            pass


def test_health_reports_a_full_and_a_read_only_store():
    from tests.filesystems import fill, read_only, small_filesystem

    with small_filesystem(4 << 20) as point:
        store = BlobStore(point / "blobs")
        fine = store.health(min_free_bytes=1 << 20)
        assert fine.ready and fine.writable and fine.total_bytes == 4 << 20
        filler = fill(point, leave_bytes=256 << 10)
        nearly = store.health(min_free_bytes=1 << 20)
        assert nearly.writable and not nearly.ready
        assert nearly.free_bytes <= 256 << 10
        assert nearly.reason.startswith("the blob store is nearly full")
        assert str(point) not in nearly.reason
        filler.unlink()
        with read_only(point):
            ro = store.health(min_free_bytes=1 << 20)
            assert not ro.writable and not ro.ready
            assert ro.reason == "the blob store is not writable (Read-only file system)"
        assert store.health(min_free_bytes=1 << 20).ready           # recovered
        assert [p.name for p in (point / "blobs").iterdir()] == []  # no probe left behind
