"""Reading ``.npz`` archives that came from outside: array headers before any data, then
the data in blocks; writing ``.npz`` archives a block at a time.

Both the mesh reader and the API's upload parser decide from the headers (shape, dtype)
whether to read an array at all, so nothing is allocated for a declared size that breaks a
limit and no pickle is ever loaded. An upload's arrays are then read as :class:`NpyMember`
blocks along axis 0 (stored or deflated members alike, through :mod:`zipfile`, so the
member's CRC is still checked) and written back with :func:`write_npz`, which takes arrays in
memory or in a file: an archive of hundreds of MiB is validated and rewritten holding a few
MiB of it (issue 16, defect 11). :func:`npz_arrays` and :func:`npz_bytes` are the plain
in-memory round trip for trusted data (stored models, results); :func:`npz_parts` gives a
response body as the pieces it is sent in, the arrays stored as they are not copied
(:func:`npz_body`: in one buffer).
"""

from __future__ import annotations

import functools
import io
import math
import mmap
import re
import struct
import tokenize
import zipfile
import zlib

from pathlib import Path
from typing import Any, BinaryIO, Callable, Iterator, Mapping

import numpy as np

from models_store.atomic import MAP_ALIGNMENT, aligned_member, padding_extra
from service.io.arrays import BLOCK_BYTES, blocks

try:   # zlib-ng's CRC-32 (folded carry-less multiplies): the same values, ~13x zlib 1.2's speed
    from zlib_ng.zlib_ng import crc32
except ImportError:                      # pragma: no cover - a declared dependency
    from zlib import crc32

#: what numpy and zipfile raise on a corrupt archive (RuntimeError: unsupported zip features)
ZIP_ERRORS = (ValueError, OSError, EOFError, KeyError, RuntimeError, struct.error,
              zipfile.BadZipFile, zlib.error)


#: what NumPy's header parser (``ast.literal_eval`` after ``tokenize``) raises on a
#: malformed header besides ValueError: a truncated literal, deep nesting, a wrong type
_HEADER_ERRORS = (SyntaxError, tokenize.TokenError, TypeError, RecursionError, MemoryError)


def npy_header(archive: zipfile.ZipFile, member: str | zipfile.ZipInfo) -> tuple[tuple[int, ...], np.dtype]:
    """Shape and dtype of one ``.npy`` member, from its header only.

    Raises ``ValueError`` for a .npy format other than 1.0/2.0 or a header that is not the
    dictionary literal numpy writes (e.g. one that cannot even be tokenized), and the
    :data:`ZIP_ERRORS` of a corrupt member; callers turn them into their format's error.
    """
    with archive.open(member) as f:
        shape, _, dtype = _read_header(f)
    return shape, dtype


#: the header NumPy writes (``{'descr': '<f4', 'fortran_order': False, 'shape': (1, 150, 3), }``
#: padded with spaces and a newline), for a plain dtype: read without NumPy's parser
_PLAIN_HEADER = re.compile(rb"\{'descr': '([<>|=][a-zA-Z][0-9]{0,4})', 'fortran_order': "
                           rb"(False|True), 'shape': \(((?:[0-9]{1,19}, )*[0-9]{1,19},?|)\), \} *\n")
#: NumPy's bound on a header's length (``max_header_size``): longer ones go to its parser
_MAX_PLAIN_HEADER = 10_000


def _read_header(f: BinaryIO) -> tuple[tuple[int, ...], bool, np.dtype]:
    """(shape, fortran_order, dtype) of the ``.npy`` stream ``f``, left at its first data byte.

    A header in the form NumPy writes for a plain dtype (:data:`_PLAIN_HEADER`) is read by a
    regular expression; any other goes to NumPy's parser (``ast.literal_eval`` of the
    header, twice per uploaded array: 0.1-0.2 ms of a one-frame synthesis request, issue 23),
    which also gives every error. Either way the result is NumPy's."""
    version = np.lib.format.read_magic(f)
    if version not in ((1, 0), (2, 0)):
        raise ValueError(f"unsupported .npy format version {version}; expected 1.0 or 2.0")
    prefix = f.read(2 if version == (1, 0) else 4)
    header = f.read(int.from_bytes(prefix, "little")) if len(prefix) in (2, 4) else b""
    plain = _PLAIN_HEADER.fullmatch(header) if len(header) <= _MAX_PLAIN_HEADER else None
    if plain is not None:
        descr, fortran, dims = plain.groups()
        return (tuple(int(n) for n in dims.split(b",") if n.strip()), fortran == b"True",
                np.dtype(descr.decode("ascii")))
    read = (np.lib.format.read_array_header_1_0 if version == (1, 0)
            else np.lib.format.read_array_header_2_0)
    try:
        shape, fortran_order, dtype = read(io.BytesIO(prefix + header))
    except _HEADER_ERRORS as error:
        # numpy tokenizes the header (a Python literal) before its own checks
        raise ValueError(f"malformed .npy header: {error}") from None
    if any(int(n) < 0 for n in shape):
        raise ValueError(f"malformed .npy header: negative dimension in shape {shape}")
    return tuple(int(s) for s in shape), bool(fortran_order), dtype


class NpyMember:
    """One ``.npy`` member of an open ``.npz`` archive, known from its header; its data read
    on demand, whole (:meth:`read`) or in blocks along axis 0 (:meth:`blocks`), never
    unpickled.

    Attributes
    ----------
    name : str            the member's array name (its file name without ``.npy``)
    shape : tuple of int
    dtype : np.dtype      not an object dtype (the caller refused those from the header)
    fortran_order : bool

    A read error (a truncated member, a bad CRC, a corrupt deflate stream) raises one of
    :data:`ZIP_ERRORS`; callers turn it into their format's error.
    """

    def __init__(self, archive: zipfile.ZipFile, info: zipfile.ZipInfo):
        self.archive, self.info = archive, info
        self.name = info.filename[:-4] if info.filename.endswith(".npy") else info.filename
        with archive.open(info) as f:
            self.shape, self.fortran_order, self.dtype = _read_header(f)

    @property
    def ndim(self) -> int:
        return len(self.shape)

    @property
    def nbytes(self) -> int:
        return math.prod(self.shape) * self.dtype.itemsize

    def __len__(self) -> int:
        return self.shape[0]

    def read(self) -> np.ndarray:
        """The whole array (what ``np.lib.format.read_array`` reads, its header read once
        more by :func:`_read_header`, not NumPy's parser)."""
        with self.archive.open(self.info) as f:
            shape, fortran_order, dtype = _read_header(f)
            if dtype.hasobject or dtype.itemsize == 0:
                f.seek(0)
                return np.lib.format.read_array(f, allow_pickle=False)
            values = np.empty(math.prod(shape), dtype)
            data = memoryview(values.view(np.uint8).reshape(-1))
            got = 0
            while got < len(data):
                n = f.readinto(data[got:])
                if not n:
                    raise ValueError(f"EOF: reading array data, expected {len(data)} bytes got {got}")
                got += n
        return values.reshape(shape, order="F" if fortran_order else "C")

    def _rows(self, max_bytes: int) -> tuple[tuple[int, ...], int, int] | None:
        """(row shape, bytes a row, rows a block) of :meth:`blocks`, None when the array
        comes as one block."""
        if self.ndim == 0 or (self.fortran_order and self.ndim > 1) or self.nbytes == 0:
            return None
        row_shape = self.shape[1:]
        row = math.prod(row_shape) * self.dtype.itemsize
        return row_shape, row, max(1, max_bytes // max(row, 1))

    def blocks(self, max_bytes: int) -> Iterator[tuple[int, np.ndarray]]:
        """``(first row, block)`` along axis 0, each of about ``max_bytes`` (at least one row),
        read in order from the member (a 0-d or Fortran-ordered array comes as one block: its
        rows are not contiguous in the file)."""
        rows = self._rows(max_bytes)
        if rows is None:
            yield 0, self.read()
            return
        row_shape, row, step = rows
        with self.archive.open(self.info) as f:
            _read_header(f)
            for start in range(0, self.shape[0], step):
                n = min(step, self.shape[0] - start)
                data = _read_exact(f, n * row)
                yield start, np.frombuffer(data, self.dtype).reshape((n,) + row_shape)
            if f.read(1):
                raise ValueError(f"'{self.name}' holds more data than its header declares")


class BufferMember(NpyMember):
    """One stored ``.npy`` member of an in-memory archive (:func:`buffer_members`), read
    as :class:`NpyMember` reads one; its bytes were checked against the CRC."""

    def __init__(self, name: str, data: memoryview, shape: tuple[int, ...], fortran_order: bool,
                 dtype: np.dtype):
        self.name, self._data = name, data
        self.shape, self.fortran_order, self.dtype = shape, fortran_order, dtype

    def read(self) -> np.ndarray:
        """The whole array, a writable copy (as :meth:`NpyMember.read` gives)."""
        values = np.frombuffer(self._data, self.dtype, math.prod(self.shape)).copy()
        return values.reshape(self.shape, order="F" if self.fortran_order else "C")

    def blocks(self, max_bytes: int) -> Iterator[tuple[int, np.ndarray]]:
        """As :meth:`NpyMember.blocks` (read-only views of the archive's bytes)."""
        rows = self._rows(max_bytes)
        if rows is None:
            yield 0, self.read()
            return
        row_shape, row, step = rows
        for start in range(0, self.shape[0], step):
            n = min(step, self.shape[0] - start)
            yield start, np.frombuffer(self._data[start * row:(start + n) * row],
                                       self.dtype).reshape((n,) + row_shape)


#: a zip's local file header, central directory header and end record (APPNOTE.TXT 4.3.7,
#: 4.3.12, 4.3.16), little-endian
_LOCAL = struct.Struct("<IHHHHHIIIHH")
_CENTRAL = struct.Struct("<IHHHHHHIIIHHHHHII")
_END = struct.Struct("<IHHHHIIH")
#: their signatures
_LOCAL_SIGNATURE, _CENTRAL_SIGNATURE, _END_SIGNATURE = 0x04034B50, 0x02014B50, 0x06054B50


def buffer_members(data: bytes | bytearray) -> list[BufferMember] | None:
    """The members of an in-memory ``.npz`` whose every member is a plain stored ``.npy``
    (what ``np.savez`` and the client SDK write), read from the zip's records directly, in
    the central directory's order; None for any other archive, which ``zipfile`` then reads
    and refuses with its own errors.

    Issue 23: a one-frame synthesis request's body through :class:`zipfile.ZipFile` and
    :class:`NpyMember` took 0.16-0.25 ms with the caches a frame leaves, 0.05 ms this way.
    Accepted only where ``zipfile`` reads the same bytes without complaint: the end record
    at the very end (no comment, nothing before the archive), no zip64 value, entries
    neither encrypted nor compressed nor patched (flags only UTF-8 names), the local
    header's name the directory's, each member's data the length its header declares and its
    CRC-32 the directory's, and a plain header of a non-object dtype.
    """
    try:
        return _buffer_members(memoryview(data))
    except (struct.error, UnicodeDecodeError, ValueError, *_HEADER_ERRORS):
        return None


def _buffer_members(buffer: memoryview) -> list[BufferMember] | None:
    end = len(buffer) - _END.size
    if end < 0:
        return None
    signature, disk, start_disk, on_disk, count, size, start, comment = _END.unpack_from(buffer, end)
    if (signature != _END_SIGNATURE or disk or start_disk or on_disk != count or comment
            or start + size != end or 0xFFFFFFFF in (size, start) or 0xFFFF == count):
        return None
    members: list[BufferMember] = []
    at = start
    for _ in range(count):
        (signature, _made, needed, flags, method, _time, _date, crc, packed, unpacked,
         name_length, extra_length, comment_length, _disk, _internal, _external,
         local) = _CENTRAL.unpack_from(buffer, at)
        raw_name = bytes(buffer[at + _CENTRAL.size:at + _CENTRAL.size + name_length])
        at += _CENTRAL.size + name_length + extra_length + comment_length
        if (signature != _CENTRAL_SIGNATURE or flags & ~0x800 or method or packed != unpacked
                or needed > zipfile.MAX_EXTRACT_VERSION or 0xFFFFFFFF in (packed, local) or at > end):
            return None
        name = raw_name.decode("utf-8" if flags & 0x800 else "cp437")
        local_signature, *_, local_name, local_extra = _LOCAL.unpack_from(buffer, local)
        begin = local + _LOCAL.size + local_name + local_extra
        if (local_signature != _LOCAL_SIGNATURE or not name.endswith(".npy") or begin + packed > start
                or bytes(buffer[local + _LOCAL.size:local + _LOCAL.size + local_name]) != raw_name):
            return None
        member = buffer[begin:begin + packed]
        if crc32(member) != crc:
            return None
        f = io.BytesIO(member[:min(packed, 16 + _MAX_PLAIN_HEADER)])
        shape, fortran_order, dtype = _read_header(f)
        offset = f.tell()
        if dtype.hasobject or dtype.itemsize == 0 or offset + math.prod(shape) * dtype.itemsize != packed:
            return None
        members.append(BufferMember(name[:-4], member[offset:], shape, fortran_order, dtype))
    return members if at == end else None


def _read_exact(f: BinaryIO, size: int) -> bytes:
    """``size`` bytes of ``f`` (EOFError if it ends first)."""
    data = f.read(size)
    if len(data) == size:
        return data
    parts = [data]
    got = len(data)
    while got < size:
        more = f.read(size - got)
        if not more:
            raise EOFError(f"the member ends after {got} of {size} bytes")
        parts.append(more)
        got += len(more)
    return b"".join(parts)


def write_npz(target: BinaryIO, arrays: Mapping[str, Any],
              dtypes: Mapping[str, Any] | None = None, max_bytes: int = BLOCK_BYTES) -> None:
    """Write an uncompressed ``.npz`` (what ``np.savez`` writes) a block at a time.

    Parameters
    ----------
    target : seekable binary file
    arrays : name → array in memory, or in a file (an object with ``shape``, ``dtype`` and
             ``blocks(max_bytes)``, e.g. :class:`NpyMember`), written in C order
    dtypes : name → dtype to cast to while writing (default: each array's own)
    max_bytes : int   about how much of an array is held at a time
    """
    dtypes = dtypes or {}
    with zipfile.ZipFile(target, mode="w", compression=zipfile.ZIP_STORED,
                         allowZip64=True) as archive:
        for name, values in arrays.items():
            if not (hasattr(values, "blocks") and hasattr(values, "shape")):
                values = np.asarray(values)
            dtype = np.dtype(dtypes.get(name, values.dtype))
            if dtype.hasobject:
                raise ValueError(f"'{name}' holds Python objects; .npz blobs hold numbers only")
            header = {"descr": np.lib.format.dtype_to_descr(dtype), "fortran_order": False,
                      "shape": tuple(values.shape)}
            with archive.open(aligned_member(archive, name + ".npy"), "w", force_zip64=True) as member:
                try:
                    np.lib.format.write_array_header_1_0(member, header)
                except ValueError:  # a header over 64 KiB (a very long shape or dtype)
                    np.lib.format.write_array_header_2_0(member, header)
                for _, block in blocks(values, max_bytes):
                    member.write(np.ascontiguousarray(block, dtype=dtype).reshape(-1).view(np.uint8))


def npz_arrays(data: bytes) -> dict[str, np.ndarray]:
    """Every array of an in-memory ``.npz`` (never unpickled); a malformed member header
    raises ``ValueError`` (see :func:`npy_header`)."""
    try:
        with np.load(io.BytesIO(data), allow_pickle=False) as d:
            return {k: d[k] for k in d.files}
    except _HEADER_ERRORS as error:
        raise ValueError(f"malformed .npy header: {type(error).__name__}") from None


def npz_mapped(path: str | Path, read: Callable[[str], bool] | None = None) -> dict[str, np.ndarray]:
    """Every array of a trusted ``.npz`` file (a stored model's, checksummed by the caller),
    memory-mapped where the archive allows it.

    ``np.savez`` stores each member uncompressed: the member is a ``.npy`` file at a fixed
    offset of the archive, so its data is mapped read-only (``mmap``) instead of read —
    a load costs no copy, and pages come in (and count as resident) when they are first
    read, as page cache the kernel may drop again. Compressed members, object arrays and
    empty ones are read into memory as :func:`npz_arrays` does, and a member whose data is
    not :data:`MAP_ALIGNMENT`-aligned is copied out of the mapping. The arrays are plain
    read-only ndarrays over a memoryview of the mapping (it stays open while they live).
    Members named where ``read(name)`` is true are read into memory instead: what the
    caller reads once and drops (a mapped page, once read, stays resident while the
    mapping lives, so it would count as the process's memory without being held).

    Raises ``ValueError`` for a malformed member header and the :data:`ZIP_ERRORS` of a
    corrupt archive.
    """
    path = Path(path)
    out: dict[str, np.ndarray] = {}
    with open(path, "rb") as f, zipfile.ZipFile(f) as archive:
        mapping = None
        for info in archive.infolist():
            name = info.filename[:-4] if info.filename.endswith(".npy") else info.filename
            if (read is None or not read(name)) and info.compress_type == zipfile.ZIP_STORED and info.file_size:
                f.seek(info.header_offset)
                local = f.read(30)
                if local[:4] != b"PK\x03\x04":
                    raise zipfile.BadZipFile(f"{path.name}: bad local header of {info.filename}")
                name_len, extra_len = struct.unpack("<HH", local[26:30])
                start = info.header_offset + 30 + name_len + extra_len
                f.seek(start)
                shape, fortran, dtype = _read_header(f)
                data = f.tell()
                size = math.prod(shape) * dtype.itemsize
                if not dtype.hasobject and data + size <= start + info.file_size and size:
                    if mapping is None:
                        mapping = mmap.mmap(f.fileno(), 0, access=mmap.ACCESS_READ)
                    flat = np.frombuffer(mapping, dtype=dtype, count=math.prod(shape), offset=data)
                    if data % MAP_ALIGNMENT:          # np.savez does not align its members
                        flat = flat.copy()
                    out[name] = flat.reshape(shape, order="F" if fortran else "C")
                    continue
            with archive.open(info) as member:
                out[name] = np.lib.format.read_array(member, allow_pickle=False)
    return out


def sparse_members(name: str, m) -> dict[str, np.ndarray]:
    """A CSR matrix ``m`` as ``.npz`` members ``<name>_data``, ``_indices``, ``_indptr`` and
    ``_shape`` (2,) int64: its own arrays, so :func:`sparse_matrix` of a mapped archive
    multiplies bit for bit as ``m``."""
    m = m.tocsr()
    return {f"{name}_data": m.data, f"{name}_indices": m.indices, f"{name}_indptr": m.indptr,
            f"{name}_shape": np.array(m.shape, np.int64)}


def sparse_matrix(arrays: Mapping[str, np.ndarray], name: str):
    """The CSR matrix :func:`sparse_members` stored as ``name`` in ``arrays`` (over the
    arrays as given, e.g. mapped: no copy), None when ``arrays`` lacks it."""
    import scipy.sparse as sp

    if f"{name}_data" not in arrays:
        return None
    shape = tuple(int(x) for x in arrays[f"{name}_shape"])
    return sp.csr_matrix((arrays[f"{name}_data"], arrays[f"{name}_indices"], arrays[f"{name}_indptr"]),
                         shape=shape, copy=False)


def npz_bytes(**arrays: np.ndarray) -> bytes:
    """An uncompressed in-memory ``.npz`` of ``arrays``."""
    buffer = io.BytesIO()
    np.savez(buffer, **arrays)
    return buffer.getvalue()


#: 1980-01-01 00:00 in DOS form (what :func:`models_store.atomic.aligned_member` stamps)
_DOS_TIME, _DOS_DATE = 0, (1 << 5) | 1
#: version 2.0 (stored members, no zip64)
_VERSION = 20
#: a body this large (or a member) needs zip64 records: written by :func:`write_npz` instead
_ZIP32_LIMIT = 0xFFFFFFFF - (1 << 20)


@functools.lru_cache(maxsize=256)
def _npy_header(dtype: np.dtype, shape: tuple[int, ...]) -> bytes:
    """The ``.npy`` header NumPy writes for ``dtype`` and ``shape`` (padded to 64 bytes);
    remembered, since a server's answers repeat the same few (NumPy's writer is ~10 µs a
    member with a frame's cold caches)."""
    header = io.BytesIO()
    fields = {"descr": np.lib.format.dtype_to_descr(dtype), "fortran_order": False,
              "shape": tuple(int(n) for n in shape)}
    try:
        np.lib.format.write_array_header_1_0(header, fields)
    except ValueError:  # a header over 64 KiB (a very long shape or dtype)
        np.lib.format.write_array_header_2_0(header, fields)
    return header.getvalue()


class NpzParts:
    """An uncompressed ``.npz`` (what ``np.savez`` writes) as the pieces a response sends in
    order: :func:`npz_parts`' answer.

    Attributes
    ----------
    pieces : tuple of bytes or memoryview (format ``B``)   the archive's bytes, in order: the
             large members' data as views of their arrays, everything between joined
    size : int   the archive's length in bytes (also ``len(parts)``)
    """

    __slots__ = ("pieces", "size")

    def __init__(self, pieces: tuple[bytes | memoryview, ...], size: int):
        self.pieces, self.size = pieces, size

    def __len__(self) -> int:
        return self.size

    def join(self) -> memoryview:
        """The whole archive in one buffer (each piece copied once)."""
        if len(self.pieces) == 1:
            return memoryview(self.pieces[0]).cast("B")
        body = np.empty(self.size, np.uint8)
        at = 0
        for piece in self.pieces:
            n = len(piece)
            body[at:at + n] = np.frombuffer(piece, np.uint8)
            at += n
        return body.data


#: a member's data of at least this many bytes is a piece of its own (a view of the array,
#: not copied); smaller data is joined with the headers around it (fewer, larger writes)
PIECE_BYTES = 1 << 16


def _stored(values: np.ndarray, dtype: np.dtype) -> np.ndarray:
    """``values`` as its member stores them, flat uint8 in C order: a view of ``values``
    when it is C-contiguous of ``dtype`` already, else converted once into a new array
    (float32 → float16 by :func:`service.io.half.to_float16`, NumPy's rounding; others by
    ``np.copyto`` with ``casting="unsafe"``, as ``astype``)."""
    if values.dtype == dtype and values.flags.c_contiguous:
        return values.reshape(-1).view(np.uint8)
    out = np.empty(values.size, dtype)
    if out.size:
        if dtype == np.float16 and values.dtype == np.float32:
            from service.io.half import to_float16   # Numba: at the first half map

            to_float16(values, out=out.view(np.uint16))
        else:
            np.copyto(out.reshape(values.shape), values, casting="unsafe")
    return out.view(np.uint8)


def npz_parts(arrays: Mapping[str, Any], dtypes: Mapping[str, Any] | None = None) -> NpzParts:
    """An uncompressed ``.npz`` of ``arrays`` (what ``np.savez`` writes, read by ``np.load``)
    as the pieces of a response body, without copying the arrays that are stored as they
    are (issue 23, the per-frame HTTP route).

    ``np.savez`` copies each array into ``tobytes()``, zipfile copies it into the
    ``BytesIO`` and ``getvalue()`` once more. Here an array that is C-contiguous in the
    dtype it is stored as is not copied at all: its member's data is a piece of its own, a
    view of the array (at least :data:`PIECE_BYTES`; smaller ones are joined with the zip
    and ``.npy`` headers around them), and the zip's CRC-32 is computed over it in place
    (zlib-ng's: 0.16 ms for 9 MB against 2.15 ms for zlib 1.2's, 2 cores, load 1.7). An
    array of another dtype or layout is converted (or copied) once. Each member's data
    starts at a multiple of :data:`MAP_ALIGNMENT` (a padding extra record, as
    :func:`models_store.atomic.aligned_member`), so a reader can view the arrays in the body
    without copying them. The caller must not write the arrays while the pieces are in use
    (a synthesis answer's arrays are its own). Bodies of 4 GiB or more (zip64) are written
    by :func:`write_npz`, as one piece.

    Parameters
    ----------
    arrays : name → array (any shape; object arrays refused)
    dtypes : name → dtype to store the array as (default its own)

    Returns
    -------
    NpzParts   the archive's pieces; ``.join()`` is the archive in one buffer
    """
    dtypes = dtypes or {}
    members = []
    offset = 0
    for name, values in arrays.items():
        values = np.asarray(values)
        dtype = np.dtype(dtypes.get(name, values.dtype))
        if dtype.hasobject or values.dtype.hasobject:
            raise ValueError(f"'{name}' holds Python objects; .npz blobs hold numbers only")
        filename = (name + ".npy").encode()
        header = _npy_header(dtype, values.shape)
        extra = padding_extra(offset + _LOCAL.size + len(filename))
        members.append((offset, filename, extra, header, values, dtype))
        offset += _LOCAL.size + len(filename) + len(extra) + len(header) + values.size * dtype.itemsize
    directory = offset
    total = directory + sum(_CENTRAL.size + len(m[1]) for m in members) + _END.size
    if total > _ZIP32_LIMIT or len(members) > 0xFFFF:
        buffer = io.BytesIO()
        write_npz(buffer, arrays, dtypes)
        body = buffer.getbuffer()
        return NpzParts((body,), len(body))
    pieces: list[bytes | memoryview] = []
    joined = bytearray()          # the bytes since the last piece of its own
    central = bytearray()
    for start, filename, extra, header, values, dtype in members:
        data = _stored(values, dtype)
        size = len(header) + data.size
        crc = crc32(data, crc32(header))
        joined += _LOCAL.pack(_LOCAL_SIGNATURE, _VERSION, 0, zipfile.ZIP_STORED, _DOS_TIME, _DOS_DATE,
                              crc, size, size, len(filename), len(extra))
        joined += filename + extra + header
        if data.size >= PIECE_BYTES:
            pieces += [bytes(joined), data.data]
            joined.clear()
        else:
            joined += data.data
        central += _CENTRAL.pack(_CENTRAL_SIGNATURE, _VERSION, _VERSION, 0, zipfile.ZIP_STORED,
                                 _DOS_TIME, _DOS_DATE, crc, size, size, len(filename), 0, 0, 0,
                                 0, 0o644 << 16, start) + filename
    joined += central
    joined += _END.pack(_END_SIGNATURE, 0, 0, len(members), len(members), len(central), directory, 0)
    pieces.append(bytes(joined))
    return NpzParts(tuple(pieces), total)


def npz_body(arrays: Mapping[str, Any], dtypes: Mapping[str, Any] | None = None) -> memoryview:
    """:func:`npz_parts` of ``arrays`` in one buffer (each array copied or converted once,
    the archive's bytes the same).

    Returns
    -------
    memoryview of bytes (format ``B``), the whole archive
    """
    return npz_parts(arrays, dtypes).join()
