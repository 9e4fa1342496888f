"""NPZ headers: hostile .npy headers are a ValueError the callers turn into a 422; response
bodies as pieces (npz_parts) or in one buffer (npz_body)."""

import io
import struct
import zipfile

import numpy as np
import pytest

from service.io.errors import MeshFormatError
from service.io.mesh_npz import read_npz
from models_store.atomic import MAP_ALIGNMENT
from service.io.npz import PIECE_BYTES, ZIP_ERRORS, npy_header, npz_body, npz_parts


def _with_vertices_header(header: bytes) -> bytes:
    """An .npz of vertices and faces whose vertices.npy header is replaced by `header`."""
    buffer = io.BytesIO()
    np.savez(buffer, vertices=np.zeros((3, 3)), faces=np.array([[0, 1, 2]]))
    source, out = zipfile.ZipFile(buffer), io.BytesIO()
    with zipfile.ZipFile(out, "w") as target:
        for info in source.infolist():
            raw = source.read(info)
            if info.filename == "vertices.npy":
                length = int.from_bytes(raw[8:10], "little")
                padded = header.ljust(length - 1) + b"\n"
                raw = raw[:10] + padded + raw[10 + length :]
            target.writestr(info, raw)
    return out.getvalue()


HOSTILE = b"{'descr': __import_('os').system('true'), 'fortran_order': (("  # cannot be tokenized


def test_untokenizable_npy_header_is_a_value_error_not_a_token_error():
    data = _with_vertices_header(HOSTILE)
    with zipfile.ZipFile(io.BytesIO(data)) as archive, pytest.raises(ValueError, match="malformed .npy header"):
        npy_header(archive, "vertices.npy")
    assert issubclass(ValueError, ZIP_ERRORS)


def test_mesh_npz_with_a_hostile_header_is_a_mesh_format_error():
    with pytest.raises(MeshFormatError, match="cannot read the header of 'vertices'.*malformed .npy header"):
        read_npz(_with_vertices_header(HOSTILE))


# -- more hostile headers (issue 16, defect 9) ----------------------------------------
from service.io.mesh import read_npz as read_mesh_npz
from service.io.npz import npz_arrays, npz_bytes


def _member(header: bytes) -> bytes:
    """A .npy member (format 1.0) with ``header`` as its header text."""
    padded = header + b" " * ((64 - (10 + len(header) + 1) % 64) % 64) + b"\n"
    return b"\x93NUMPY\x01\x00" + len(padded).to_bytes(2, "little") + padded


def _archive(**members: bytes) -> bytes:
    buffer = io.BytesIO()
    with zipfile.ZipFile(buffer, "w") as z:
        for name, data in members.items():
            z.writestr(f"{name}.npy", data)
    return buffer.getvalue()


HOSTILE_HEADERS = [
    b"{'descr': __import__('os').system('true'",          # unterminated: tokenize.TokenError
    b"{'descr': '<f4', 'fortran_order': False, 'shape': (3,",
    b"{'descr': '<f4' 'x",
    b"(" * 200,
    b"{'descr': __import__('os'), 'fortran_order': False, 'shape': (3,)}",   # not a literal
    b"{'descr': '<f4', 'fortran_order': False, 'shape': (-1, 3)}",
]


@pytest.mark.parametrize("header", HOSTILE_HEADERS)
def test_hostile_npy_headers_are_value_errors(header):
    data = _archive(vertices=_member(header))
    with zipfile.ZipFile(io.BytesIO(data)) as archive:
        with pytest.raises(ValueError):
            npy_header(archive, "vertices.npy")
    with pytest.raises(ZIP_ERRORS):
        npz_arrays(data)
    with pytest.raises(MeshFormatError):
        read_mesh_npz(data)


def test_a_good_header_reads_back():
    data = npz_bytes(vertices=np.zeros((4, 3), np.float32))
    with zipfile.ZipFile(io.BytesIO(data)) as archive:
        assert npy_header(archive, "vertices.npy") == ((4, 3), np.dtype(np.float32))


def test_npz_mapped_maps_stored_members_and_reads_the_rest(tmp_path):
    """``npz_mapped`` (stored models' archives): every member equal to ``np.load``'s, the
    uncompressed non-empty ones read-only views of one mapping (C and Fortran order), the
    empty, string and compressed ones read."""
    import mmap

    from service.io.npz import MAP_ALIGNMENT, npz_mapped

    arrays = {"x": np.arange(12.0).reshape(3, 4), "f": np.asfortranarray(np.arange(6, dtype=np.int32).reshape(2, 3)),
              "e": np.zeros((0, 3)), "s": np.float64(3.5), "u": np.array(["ab", "c"])}
    for save in (np.savez, np.savez_compressed):
        save(tmp_path / "a.npz", **arrays)
        out = npz_mapped(tmp_path / "a.npz")
        assert out.keys() == arrays.keys()
        for k, v in arrays.items():
            assert out[k].dtype == np.asarray(v).dtype and out[k].shape == np.shape(v), k
            np.testing.assert_array_equal(out[k], v)
        views = {k for k, v in out.items() if isinstance(v.base, np.ndarray)
                 and isinstance(v.base.base, memoryview) and isinstance(v.base.base.obj, mmap.mmap)}
        # a stored member is mapped where its data is MAP_ALIGNMENT-aligned, copied where not
        assert views <= ({"x", "f", "s", "u"} if save is np.savez else set())
        assert all(not out[k].flags.writeable and out[k].ctypes.data % MAP_ALIGNMENT == 0 for k in views)
        assert all(v.flags.aligned for v in out.values())
        assert out["f"].flags.f_contiguous


def test_npz_mapped_reads_the_members_asked_for_and_csr_members_round_trip(tmp_path):
    """``read``: the named members are read into memory (the rest still mapped), equal;
    ``sparse_members``/``sparse_matrix``: a CSR matrix stored and mapped is the same arrays."""
    import scipy.sparse as sp

    from service.io.atomic import write_npz
    from service.io.npz import npz_mapped, sparse_matrix, sparse_members
    from service.methods.footprint import file_mapped

    m = sp.random(40, 30, density=0.2, format="csr", random_state=np.random.default_rng(3))
    write_npz(tmp_path / "a.npz", {"x": np.arange(100.0), "y": np.arange(50, dtype=np.int32), **sparse_members("m", m)})
    out = npz_mapped(tmp_path / "a.npz", read=lambda k: k == "y")
    assert file_mapped(out["x"]) and not file_mapped(out["y"]) and out["y"].flags.writeable
    np.testing.assert_array_equal(out["y"], np.arange(50))
    back = sparse_matrix(out, "m")
    assert back.shape == (40, 30) and file_mapped(back.data) and sparse_matrix(out, "other") is None
    for a in ("data", "indices", "indptr"):
        np.testing.assert_array_equal(getattr(back, a), getattr(m, a))
    v = np.random.default_rng(4).normal(size=30)
    assert np.array_equal(back @ v, m @ v)


def _body_arrays():
    rng = np.random.default_rng(11)
    return {"vertices": rng.standard_normal((2, 5, 3)).astype(np.float32),
            "faces": np.arange(12, dtype=np.int32).reshape(4, 3)[:, ::-1],   # not contiguous
            "normal_map": rng.standard_normal((2, 3, 4, 3)).astype(np.float32),
            "empty": np.zeros((0, 3)), "scalar": np.float64(2.5), "name": np.array("ab")}


def test_npz_body_is_what_np_load_reads_with_aligned_members():
    arrays = _body_arrays()
    arrays["normal_map"][0, 0, 0] = [np.inf, 7e4, np.nan]
    body = npz_body(arrays, {"normal_map": np.float16, "faces": np.int64})
    assert isinstance(body, memoryview) and body.format == "B"
    archive = zipfile.ZipFile(io.BytesIO(body))
    assert archive.testzip() is None                    # every member's CRC-32
    with np.load(io.BytesIO(body), allow_pickle=False) as loaded:
        assert loaded.files == list(arrays)
        for name, values in arrays.items():
            want = np.asarray(values)
            if name == "normal_map":
                with np.errstate(over="ignore", invalid="ignore"):
                    want = want.astype(np.float16)
            elif name == "faces":
                want = want.astype(np.int64)
            got = loaded[name]
            assert got.dtype == want.dtype and got.shape == want.shape, name
            assert got.tobytes() == want.tobytes(), name
    raw = bytes(body)
    for info in archive.infolist():       # the member's .npy (and so its data) 64-aligned
        name_len, extra_len = struct.unpack("<HH", raw[info.header_offset + 26:info.header_offset + 30])
        assert (info.header_offset + 30 + name_len + extra_len) % MAP_ALIGNMENT == 0


def test_npz_body_writes_zip64_bodies_as_write_npz(monkeypatch):
    import service.io.npz as npz

    arrays = _body_arrays()
    monkeypatch.setattr(npz, "_ZIP32_LIMIT", 100)
    body = npz_body(arrays, {"normal_map": np.float16})
    with np.load(io.BytesIO(body), allow_pickle=False) as loaded:
        assert loaded["normal_map"].dtype == np.float16
        np.testing.assert_array_equal(loaded["vertices"], arrays["vertices"])


def test_npz_body_refuses_object_arrays():
    with pytest.raises(ValueError, match="Python objects"):
        npz_body({"x": np.array([None, 1], dtype=object)})


def _answer_arrays():
    rng = np.random.default_rng(23)
    return {"vertices": rng.standard_normal((1, 6000, 3)).astype(np.float32),
            "clamped": np.zeros(1, np.float32),
            "faces": np.arange(30000, dtype=np.int32).reshape(-1, 3)[:, ::-1],   # not contiguous
            "displacement": rng.standard_normal((1, 128, 160)).astype(np.float32),
            "normal_map": rng.standard_normal((1, 128, 96, 3)).astype(np.float16),
            "scalar": np.float64(2.5)}


@pytest.mark.parametrize("dtypes, digest", [
    ({"displacement": np.float16}, "a733dc53a134cafcd838aeabe156ccbff30a16434ce9d10ba4ffe23ed8994234"),
    (None, "2dfa8f43e810a4d578a9bb6a4bf2b861cfe36ade52d82b5f29ffd29007845184")])
def test_npz_parts_are_the_bytes_npz_body_wrote_before_with_large_arrays_not_copied(dtypes, digest):
    """issue 23: the pieces joined are byte for byte what the one-buffer npz_body answered
    before them (sha256 of its body for these seeded arrays, zlib's CRC-32 in it); the
    members stored as they are (C-contiguous, their own dtype, >= PIECE_BYTES) are views of
    the arrays, the converted and the small ones are not."""
    import hashlib

    arrays = _answer_arrays()
    parts = npz_parts(arrays, dtypes)
    joined = b"".join(bytes(piece) for piece in parts.pieces)
    assert len(parts) == len(joined) and hashlib.sha256(joined).hexdigest() == digest
    assert bytes(npz_body(arrays, dtypes)) == joined
    views = [name for name, values in arrays.items()
             if any(np.shares_memory(np.frombuffer(p, np.uint8), np.asarray(values))
                    for p in parts.pieces)]
    assert views == ["vertices", "normal_map"] if dtypes else \
        views == ["vertices", "displacement", "normal_map"]
    assert all(arrays[name].nbytes >= PIECE_BYTES for name in views)
    # a piece before each large member's data (faces: converted, so a copy) and the last
    assert len(parts.pieces) == 2 * (3 if dtypes else 4) + 1


def _npy(values, header: bytes | None = None, version=(1, 0)) -> bytes:
    """The .npy bytes NumPy writes for ``values`` (its header replaced by ``header``)."""
    buffer = io.BytesIO()
    np.lib.format.write_array(buffer, values, version=version)
    raw = buffer.getvalue()
    if header is None:
        return raw
    size = 2 if version == (1, 0) else 4
    length = int.from_bytes(raw[8:8 + size], "little")
    return raw[:8] + len(header).to_bytes(size, "little") + header + raw[8 + size + length:]


@pytest.mark.parametrize("values", [
    np.zeros((1, 150, 3), np.float32), np.arange(7, dtype=">i8"), np.float64(2.5),
    np.zeros((0, 3)), np.array(["ab", "c"]), np.array([True, False]),
    np.asfortranarray(np.arange(12.0).reshape(3, 4)), np.zeros(3, "M8[ns]"),
    np.zeros(2, [("x", "<f4"), ("y", "<i2")]), np.zeros((2, 1, 1, 1, 1), np.complex128)])
@pytest.mark.parametrize("version", [(1, 0), (2, 0)])
def test_headers_and_arrays_read_as_numpy_reads_them(values, version):
    """issue 23: a header in NumPy's own form is read without NumPy's parser (a regular
    expression), any other by NumPy's; either way shape, order, dtype and data are NumPy's."""
    from service.io.npz import NpyMember, _read_header

    raw = _npy(values, version=version)
    want = np.lib.format.read_array(io.BytesIO(raw))
    stream = io.BytesIO(raw)
    shape, fortran, dtype = _read_header(stream)
    assert (shape, dtype) == (want.shape, want.dtype) and fortran == (
        want.ndim > 1 and want.flags.f_contiguous and not want.flags.c_contiguous)
    assert stream.tell() == len(raw) - want.nbytes
    buffer = io.BytesIO()
    with zipfile.ZipFile(buffer, "w") as archive:
        archive.writestr("v.npy", raw)
    archive = zipfile.ZipFile(buffer)
    got = NpyMember(archive, archive.infolist()[0]).read()
    assert got.dtype == want.dtype and got.shape == want.shape and got.flags.writeable
    assert got.tobytes("A") == want.tobytes("A") and got.flags.f_contiguous == want.flags.f_contiguous


@pytest.mark.parametrize("header, error", [
    (b"{'shape': (2,), 'fortran_order': False, 'descr': '<f8', }" + b" " * 6 + b"\n", None),
    (b"{'descr':'<f8','fortran_order':False,'shape':(2,)}" + b" " * 12 + b"\n", None),
    (b"{'descr': '<f8', 'fortran_order': False, 'shape': (2,), }" + b" " * 20000 + b"\n",
     "Header info length"),
    (b"{'descr': '<f8', 'fortran_order': False, 'shape': (-2,), }\n", "shape"),
    (b"{'descr': '<f8', 'fortran_order': 0, 'shape': (2,), }\n", "fortran_order")])
def test_other_headers_go_to_numpy_s_parser(header, error):
    from service.io.npz import _read_header

    stream = io.BytesIO(_npy(np.array([1.0, 2.0]), header))
    if error is None:
        assert _read_header(stream) == ((2,), False, np.dtype("<f8"))
    else:
        with pytest.raises(ValueError, match=error):
            _read_header(stream)


def _arrays_for_buffers() -> dict[str, np.ndarray]:
    rng = np.random.default_rng(5)
    return {"markers": rng.normal(size=(3, 20, 3)).astype(np.float32), "fps": np.float64(30),
            "ids": np.arange(7, dtype=">i8"), "empty": np.zeros((0, 3)),
            "fortran": np.asfortranarray(rng.normal(size=(3, 4))), "text": np.array(["ab", "c"]),
            "record": np.zeros(2, [("x", "<f4"), ("y", "<i2")])}


def _savez(**arrays) -> bytes:
    buffer = io.BytesIO()
    np.savez(buffer, **arrays)
    return buffer.getvalue()


@pytest.mark.parametrize("writer", ["np.savez", "npz_body"])
def test_buffer_members_read_what_zipfile_reads(writer):
    """issue 23: a plain stored archive in memory is read from its records directly, the
    members in the directory's order, every array (and every block of it) bit for bit the
    zipfile reader's, writable copies from read()."""
    from service.io.npz import NpyMember, buffer_members

    arrays = _arrays_for_buffers()
    data = _savez(**arrays) if writer == "np.savez" else bytes(npz_body(arrays))
    members = buffer_members(data)
    archive = zipfile.ZipFile(io.BytesIO(data))
    assert [m.name for m in members] == list(arrays)
    for member, info in zip(members, archive.infolist()):
        reference = NpyMember(archive, info)
        assert (member.shape, member.dtype, member.fortran_order, member.nbytes, member.ndim) == \
            (reference.shape, reference.dtype, reference.fortran_order, reference.nbytes, reference.ndim)
        got, want = member.read(), reference.read()
        assert got.flags.writeable and got.tobytes("A") == want.tobytes("A")
        assert got.flags.f_contiguous == want.flags.f_contiguous
        for (a, x), (b, y) in zip(member.blocks(100), reference.blocks(100), strict=True):
            assert a == b and x.tobytes() == y.tobytes()
    from service.app.uploads import NpzUpload
    from service.io.arrays import ArraySpec
    from service.io.npz import BufferMember

    specs = {name: ArraySpec(tuple(f"{name}{i}" for i in range(np.ndim(v))), "fiubUV")
             for name, v in arrays.items()}
    upload = NpzUpload(data, specs, 1 << 20)
    assert all(isinstance(m.member, BufferMember) for m in upload.members().values())
    assert all(np.array_equal(upload.load()[k], v) for k, v in arrays.items())


def _edited(data: bytes, at: int, value: bytes) -> bytes:
    return data[:at] + value + data[at + len(value):]


def _unusual_archives() -> dict[str, bytes]:
    plain = _savez(markers=np.ones((1, 4, 3)))
    compressed = io.BytesIO()
    np.savez_compressed(compressed, markers=np.ones((1, 4, 3)))
    commented = io.BytesIO(plain)
    with zipfile.ZipFile(commented, "a") as archive:
        archive.comment = b"note"
    text = io.BytesIO()
    with zipfile.ZipFile(text, "w") as archive:
        archive.writestr("notes.txt", b"hello")
    crc_at = plain.index(b"PK\x01\x02") + 16
    name_at = 30                                       # the local header's name
    data_at = plain.index(b"\x93NUMPY") + 128          # a data byte
    return {"deflated": compressed.getvalue(), "commented": commented.getvalue(),
            "prefixed": b"MZ" + plain, "not an array": text.getvalue(), "truncated": plain[:-30],
            "bad CRC": _edited(plain, data_at, b"\x01"),
            "directory CRC": _edited(plain, crc_at, b"\0\0\0\0"),
            "local name": _edited(plain, name_at, b"n"),
            "object array": _savez(values=np.array([{"a": 1}], dtype=object))}


@pytest.mark.parametrize("name", list(_unusual_archives()))
def test_buffer_members_leave_every_other_archive_to_zipfile(name):
    """Anything but a plain stored archive (compressed, commented, shifted, cut short, a bad
    CRC, names that differ, another file, an object array) is None; NpzUpload then gives
    zipfile's own verdict, as before the direct reader existed."""
    from service.app.uploads import NpzUpload
    from service.io.errors import FormatError
    from service.io.npz import buffer_members
    from service.io.arrays import ArraySpec

    data = _unusual_archives()[name]
    assert buffer_members(data) is None
    specs = {"markers": ArraySpec(("F", "M", 3), "f", False), "values": ArraySpec(("F",), "O", False)}
    try:
        upload = NpzUpload(data, specs, 1 << 20, what="request")
        arrays = upload.load()
    except FormatError as error:
        outcome = str(error)
    else:
        outcome = {k: v.tolist() for k, v in arrays.items()}
    expected = {"deflated": {"markers": np.ones((1, 4, 3)).tolist()},
                "commented": {"markers": np.ones((1, 4, 3)).tolist()},
                "prefixed": {"markers": np.ones((1, 4, 3)).tolist()},
                "not an array": "the request .npz holds 'notes.txt', which is not an array (.npy)",
                "truncated": "the request is not a readable .npz archive",
                "bad CRC": "cannot read the header of 'markers' in the request .npz: Bad CRC-32",
                "directory CRC": "cannot read the header of 'markers' in the request .npz: Bad CRC-32",
                "local name": "cannot read the header of 'markers' in the request .npz: File name in directory",
                "object array": "'values' holds Python objects"}[name]
    if isinstance(expected, str):
        assert isinstance(outcome, str) and outcome.startswith(expected), outcome
    else:
        assert outcome == expected
