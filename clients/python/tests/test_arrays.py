"""``facesynth_client.arrays``: ``npz_bytes`` writes ``np.savez``'s members byte for byte;
``load_npz(views=True)`` gives np.load's arrays bit for bit, as read-only views of the body,
and defers to np.load for what it does not view."""

from __future__ import annotations

import io
import zipfile

import numpy as np
import pytest

from facesynth_client.arrays import load_npz, npz_bytes


def _arrays() -> dict[str, np.ndarray]:
    rng = np.random.default_rng(7)
    return {"vertices": rng.normal(size=(2, 50, 3)).astype(np.float32),
            "faces": rng.integers(0, 50, (30, 3)).astype(np.int32),
            "displacement": rng.normal(size=(2, 8, 8)).astype(np.float16),
            "clamped": np.array([0.25, 0.0]), "scalar": np.float64(3.5),
            "empty": np.zeros((0, 3), np.float32),
            "fortran": np.asfortranarray(rng.normal(size=(4, 5))),
            "big_endian": np.arange(6, dtype=">i4").reshape(2, 3)}


def _savez(arrays: dict[str, np.ndarray]) -> bytes:
    buffer = io.BytesIO()
    np.savez(buffer, **arrays)
    return buffer.getvalue()


@pytest.mark.parametrize("size", ["small", "large"])
def test_npz_bytes_members_are_np_savez_members_byte_for_byte(size):
    """Small bodies are written directly, large ones (beyond 1 MiB of data) by np.savez:
    either way a valid zip (CRCs checked by zipfile) whose members are np.save's bytes,
    C, Fortran and strided arrays, scalars, strings, records and non-ASCII names alike."""
    arrays = {**_arrays(), "strided": np.arange(24.0).reshape(4, 6)[:, ::2],
              "text": np.array(["ab", "c"]), "record": np.zeros(2, [("a", "<f4"), ("b", "<i2")]),
              "flags": np.array([True, False]), "maße": np.arange(3, dtype=np.uint8)}
    if size == "large":
        arrays["vertices"] = np.random.default_rng(1).normal(size=(3, 50_000, 3))
    body, reference = npz_bytes(**arrays), _savez(arrays)
    with zipfile.ZipFile(io.BytesIO(body)) as ours, zipfile.ZipFile(io.BytesIO(reference)) as theirs:
        assert ours.testzip() is None
        written_here = body[28:30] == b"\0\0"     # np.savez's members carry a zip64 extra field
        assert written_here == (size == "small")
        assert ours.namelist() == theirs.namelist() == [f"{name}.npy" for name in arrays]
        for member in theirs.namelist():
            assert ours.read(member) == theirs.read(member), member
    assert npz_bytes(markers=np.ones((1, 4, 3))) == npz_bytes(markers=np.ones((1, 4, 3)))   # no clock


def _server_body(arrays: dict[str, np.ndarray]) -> bytes:
    from service.io.npz import npz_body    # the server's writer (64-byte aligned members)

    return bytes(npz_body(arrays))


@pytest.mark.parametrize("encode", [lambda a: npz_bytes(**a), _server_body],
                         ids=["np.savez", "server npz_body"])
def test_views_equal_np_load_bit_for_bit_and_are_views_of_the_body(encode):
    body = encode(_arrays())
    copied, viewed = load_npz(body), load_npz(body, views=True)
    assert list(viewed) == list(copied)
    base = np.frombuffer(body, np.uint8)
    for name, value in copied.items():
        view = viewed[name]
        assert view.dtype == value.dtype and view.shape == value.shape, name
        assert view.tobytes() == value.tobytes(), name
        assert view.flags.f_contiguous == value.flags.f_contiguous, name
        assert not view.flags.writeable, name
        if view.size:
            assert np.shares_memory(view, base), name


def _deflated(arrays: dict[str, np.ndarray]) -> bytes:
    buffer = io.BytesIO()
    np.savez_compressed(buffer, **arrays)
    return buffer.getvalue()


def _commented(arrays: dict[str, np.ndarray]) -> bytes:
    buffer = io.BytesIO(npz_bytes(**arrays))
    with zipfile.ZipFile(buffer, "a") as archive:
        archive.comment = b"a trailing comment"
    return buffer.getvalue()


@pytest.mark.parametrize("encode", [_deflated, _commented], ids=["deflated", "comment"])
def test_archives_it_does_not_view_are_read_by_np_load(encode):
    body = encode(_arrays())
    viewed = load_npz(body, views=True)
    for name, value in load_npz(body).items():
        assert viewed[name].tobytes() == value.tobytes() and viewed[name].flags.writeable


def test_object_arrays_and_corrupt_bodies_are_refused_as_np_load_does():
    buffer = io.BytesIO()
    np.savez(buffer, bad=np.array([{"a": 1}], dtype=object))
    with pytest.raises(ValueError, match="allow_pickle"):
        load_npz(buffer.getvalue(), views=True)
    body = npz_bytes(**_arrays())
    with pytest.raises(zipfile.BadZipFile):
        load_npz(body[:-30], views=True)                   # truncated: np.load's error
    end = body.rindex(b"PK\x05\x06")
    cut = body[:end - 20] + body[end:]                     # the directory's last record cut short
    with pytest.raises(zipfile.BadZipFile):
        load_npz(cut, views=True)
    # a header whose shape does not fill its member is not viewed; np.load then finds the
    # member's CRC-32 wrong
    broken = body.replace(b"'shape': (2, 50, 3)", b"'shape': (2, 50, 2)")
    with pytest.raises(zipfile.BadZipFile, match="CRC"):
        load_npz(broken, views=True)


def test_corrupt_zip_records_give_np_load_s_answer():
    """Seeded single-byte corruptions of the zip records (local headers with their names,
    central directory, end record; not the CRC-32 fields, which ``views=True`` does not
    check by design): ``views=True`` answers what ``np.load`` answers, arrays or error type."""
    import struct

    body = _server_body({"vertices": np.arange(12, dtype=np.float32).reshape(1, 4, 3),
                         "clamped": np.array([0.5], np.float32)})
    spots: list[int] = []
    at = 0
    while body.startswith(b"PK\x03\x04", at):                # local headers and names
        name_len, extra_len = struct.unpack_from("<HH", body, at + 26)
        packed, = struct.unpack_from("<I", body, at + 18)
        spots += [k for k in range(at, at + 30 + name_len) if not at + 14 <= k < at + 18]
        at += 30 + name_len + extra_len + packed
    directory = at
    while body.startswith(b"PK\x01\x02", at):                # central records
        name_len, extra_len, comment_len = struct.unpack_from("<HHH", body, at + 28)
        size = 46 + name_len + extra_len + comment_len
        spots += [k for k in range(at, at + size) if not at + 16 <= k < at + 20]
        at += size
    spots += list(range(at, len(body)))                        # the end record
    assert body.startswith(b"PK\x05\x06", at) and directory < at
    rng = np.random.default_rng(3)
    for spot in rng.choice(spots, 300):
        broken = bytearray(body)
        broken[spot] ^= int(rng.choice([1, 0x80, 0xFF]))
        broken = bytes(broken)
        try:
            expected = load_npz(broken)
        except Exception as error:                        # noqa: BLE001 - np.load's own
            with pytest.raises(type(error)):
                load_npz(broken, views=True)
            continue
        viewed = load_npz(broken, views=True)
        assert {k: v.tobytes() for k, v in viewed.items()} == \
            {k: v.tobytes() for k, v in expected.items()}
