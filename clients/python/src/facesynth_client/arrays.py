"""Arrays in and out: NPZ encoding (``np.savez``'s archives, never pickles), NPZ decoding
(``allow_pickle=False``), and meshes from NumPy arrays, trimesh-like objects or files.

A *mesh* argument may be

- an object with ``.vertices`` (V,3) and ``.faces`` (T,3), and optionally ``.visual.uv``
  (V,2) — e.g. a ``trimesh.Trimesh``. Load it with ``process=False`` (and
  ``maintain_order=True``): trimesh's default processing merges vertices, which breaks the
  vertex correspondence every clip relies on;
- a mapping with ``vertices``, ``faces`` and optionally ``uv``, ``uv_faces``, ... arrays;
- a path (``str`` / :class:`os.PathLike`) of an ``.obj`` or ``.npz`` file, sent as is;
- the bytes of an ``.obj`` or ``.npz`` file (told apart by the zip signature).
"""

from __future__ import annotations

import functools
import io
import os
import tokenize
from pathlib import Path
from typing import Any, Mapping, Sequence

import numpy as np

__all__ = ["NPZ", "OBJ", "JSON", "npz_bytes", "load_npz", "mesh_arrays", "mesh_body",
           "frames_array", "is_path"]

NPZ = "application/x-npz"
OBJ = "model/obj"
JSON = "application/json"
EXR = "image/x-exr"
#: media types of marker files by suffix (they travel as multipart file parts)
MARKER_FILE_SUFFIXES = {".c3d": "application/x-c3d", ".trc": "text/x-trc", ".csv": "text/csv",
                        ".json": JSON, ".npz": NPZ}


def is_path(value: Any) -> bool:
    """Whether ``value`` names a file (``str`` or :class:`os.PathLike`)."""
    return isinstance(value, (str, os.PathLike))


def npz_bytes(**arrays: Any) -> bytes:
    """An ``.npz`` archive of ``arrays`` (no object arrays, so no pickles), as ``np.savez``
    writes it for ``np.load``: each array a stored (uncompressed) ``.npy`` member.

    Bodies up to :data:`_DIRECT_BYTES` are written here directly (:func:`_stored_npz`: a
    frame's markers in a few struct packs instead of ``zipfile``'s machinery, ~0.1 ms less
    a per-frame call); larger ones, and arrays whose ``.npy`` header is not a version-1.0
    one, by ``np.savez`` itself.

    Examples
    --------
    >>> data = npz_bytes(markers=np.zeros((2, 150, 3), np.float32))
    >>> load_npz(data)["markers"].shape
    (2, 150, 3)
    """
    clean: dict[str, np.ndarray] = {}
    for name, value in arrays.items():
        if value is None:
            continue
        array = np.asarray(value)
        if array.dtype.hasobject:
            raise TypeError(f"array {name!r} has dtype object; send numeric arrays "
                            "(object arrays would need pickles)")
        clean[name] = array
    if sum(a.nbytes for a in clean.values()) <= _DIRECT_BYTES:
        data = _stored_npz(clean)
        if data is not None:
            return data
    buffer = io.BytesIO()
    np.savez(buffer, **clean)
    return buffer.getvalue()


#: largest array data :func:`npz_bytes` writes itself (beyond, ``np.savez``: zip64 and the
#: streaming of large arrays are zipfile's)
_DIRECT_BYTES = 1 << 20
#: the DOS date of 1980-01-01, 00:00 (``np.savez`` stamps the current time; a fixed one
#: makes the same arrays the same bytes)
_DOS_DATE, _DOS_TIME = (0 << 9) | (1 << 5) | 1, 0
#: NumPy's alignment of a ``.npy`` header's end (``np.lib.format.ARRAY_ALIGN``)
_NPY_ALIGN = 64


def _stored_npz(arrays: Mapping[str, np.ndarray]) -> bytes | None:
    """A zip of ``name.npy`` members, stored, as ``np.savez`` lays them out (local header,
    ``.npy`` bytes; the central directory; its end record), or None when an array's
    header would need ``.npy`` version 2."""
    import struct
    import zlib

    pieces: list[bytes | memoryview] = []
    directory: list[bytes] = []
    offset = 0
    for name, array in arrays.items():
        fortran = array.flags.f_contiguous and not array.flags.c_contiguous   # kept, as np.save
        stored = array.T if fortran else np.ascontiguousarray(array)
        fields = (f"{{'descr': {np.lib.format.dtype_to_descr(array.dtype)!r}, "
                  f"'fortran_order': {fortran}, 'shape': {array.shape!r}, }}")
        pad = -(10 + len(fields) + 1) % _NPY_ALIGN
        header_length = len(fields) + pad + 1
        if header_length > 0xFFFF:
            return None
        header = (b"\x93NUMPY\x01\x00" + struct.pack("<H", header_length)
                  + fields.encode("latin-1") + b" " * pad + b"\n")
        data = memoryview(stored).cast("B") if array.nbytes else b""
        crc = zlib.crc32(data, zlib.crc32(header))
        size = len(header) + array.nbytes
        member = f"{name}.npy".encode("utf-8")
        flags = 0x800 if not member.isascii() else 0      # a UTF-8 name, as zipfile marks it
        local = struct.pack("<4s5H3I2H", _LOCAL_SIGNATURE, 20, flags, 0, _DOS_TIME, _DOS_DATE,
                            crc, size, size, len(member), 0)
        directory.append(struct.pack("<4s6H3I5HII", _CENTRAL_SIGNATURE, 20, 20, flags, 0,
                                     _DOS_TIME, _DOS_DATE, crc, size, size, len(member), 0,
                                     0, 0, 0, 0o600 << 16, offset) + member)
        pieces += [local, member, header, data]
        offset += len(local) + len(member) + size
    central = b"".join(directory)
    end = struct.pack("<4s4H2IH", _END_SIGNATURE, 0, 0, len(directory), len(directory),
                      len(central), offset, 0)
    return b"".join([*pieces, central, end])


def load_npz(data: bytes, *, views: bool = False) -> dict[str, np.ndarray]:
    """The arrays of an ``.npz`` archive (read with ``allow_pickle=False``).

    ``views=True``: the arrays of an uncompressed archive (what the server answers) are
    read-only views of ``data`` itself, found through the zip's central directory without
    copying them and without checking the members' CRC-32 (the HTTP body arrived complete
    over TCP; its length is the ``Content-Length``). The values are the same as
    ``np.load``'s, bit for bit. An archive it cannot view so (compressed or zip64 members,
    a trailing comment, a header that does not add up) is read by ``np.load`` instead,
    which also raises the errors of a corrupt one.
    """
    if views:
        arrays = _npz_views(data)
        if arrays is not None:
            return arrays
    with np.load(io.BytesIO(data), allow_pickle=False) as archive:
        return {name: archive[name] for name in archive.files}


#: a zip's end of central directory record, central directory header and local file
#: header (PKWARE APPNOTE.TXT 4.3.16, 4.3.12, 4.3.7): signature and fixed size
_END_SIGNATURE, _END_SIZE = b"PK\x05\x06", 22
_CENTRAL_SIGNATURE, _CENTRAL_SIZE = b"PK\x01\x02", 46
_LOCAL_SIGNATURE, _LOCAL_SIZE = b"PK\x03\x04", 30
#: a 32-bit size or offset field that defers to a zip64 record
_ZIP64_MARK = 0xFFFFFFFF
#: the newest "version needed to extract" viewed (4.5: zip64; np.savez writes 2.0 or 4.5)
_MAX_VERSION = 45
#: what NumPy's header parser (``ast.literal_eval`` after ``tokenize``) raises on a header
#: that is not the dictionary literal it writes
_HEADER_ERRORS = (ValueError, SyntaxError, TypeError, EOFError, RecursionError, MemoryError,
                  tokenize.TokenError)


def _npz_views(data: bytes) -> dict[str, np.ndarray] | None:
    """The arrays of an uncompressed ``.npz`` as views of ``data``, or None when it is not
    one this reader handles (see :func:`load_npz`)."""
    import struct

    try:
        return _walk_directory(data)
    except (struct.error, UnicodeDecodeError):       # records cut short, a name not UTF-8
        return None


def _walk_directory(data: bytes) -> dict[str, np.ndarray] | None:
    """:func:`_npz_views` itself (``struct.error`` where a record runs past the body)."""
    import struct

    buffer = memoryview(data)
    if len(buffer) < _END_SIZE or bytes(buffer[-_END_SIZE:-_END_SIZE + 4]) != _END_SIGNATURE:
        return None                                        # absent, or behind a comment
    entries, size, start = struct.unpack_from("<HII", buffer, len(buffer) - _END_SIZE + 10)
    if start == _ZIP64_MARK or size == _ZIP64_MARK or start + size > len(buffer) - _END_SIZE:
        return None
    out: dict[str, np.ndarray] = {}
    at = start
    for _ in range(entries):
        if bytes(buffer[at:at + 4]) != _CENTRAL_SIGNATURE:
            return None
        needed, flags, method = struct.unpack_from("<HHH", buffer, at + 6)
        packed, unpacked, name_len, extra_len, comment_len = struct.unpack_from(
            "<IIHHH", buffer, at + 20)
        local, = struct.unpack_from("<I", buffer, at + 42)
        raw_name = bytes(buffer[at + _CENTRAL_SIZE:at + _CENTRAL_SIZE + name_len])
        name = raw_name.decode("utf-8")
        at += _CENTRAL_SIZE + name_len + extra_len + comment_len
        # what zipfile checks before it reads a member: no flags (encryption, data
        # descriptors, ...), a version it extracts, a stored member, the same name in the
        # local header as in the directory
        if (flags or needed > _MAX_VERSION or method != 0 or packed != unpacked
                or _ZIP64_MARK in (packed, local) or not name.endswith(".npy")
                or bytes(buffer[local:local + 4]) != _LOCAL_SIGNATURE):
            return None
        local_name, local_extra = struct.unpack_from("<HH", buffer, local + 26)
        if bytes(buffer[local + _LOCAL_SIZE:local + _LOCAL_SIZE + local_name]) != raw_name:
            return None
        begin = local + _LOCAL_SIZE + local_name + local_extra
        array = _npy_view(data, begin, begin + packed)
        if array is None:
            return None
        out[name[:-4]] = array
    if at != start + size:                          # the directory's size does not add up
        return None
    return out


def _npy_view(data: bytes, begin: int, end: int) -> np.ndarray | None:
    """The ``.npy`` file at ``data[begin:end]`` as a read-only view of ``data`` (None if its
    header is not a version 1 or 2 header of a non-object array whose data fills the
    member)."""
    import struct

    magic = bytes(data[begin:begin + 8])
    if magic == b"\x93NUMPY\x01\x00":
        length_end = begin + 10
        length, = struct.unpack_from("<H", data, begin + 8) if length_end <= end else (-1,)
    elif magic == b"\x93NUMPY\x02\x00":
        length_end = begin + 12
        length, = struct.unpack_from("<I", data, begin + 8) if length_end <= end else (-1,)
    else:
        return None
    offset = length_end + length
    if length < 0 or offset > end:
        return None
    parsed = _npy_header(bytes(data[begin:offset]))
    if parsed is None:
        return None
    shape, fortran_order, dtype, count = parsed
    if offset + count * dtype.itemsize != end:
        return None
    flat = np.frombuffer(data, dtype=dtype, count=count, offset=offset)
    if fortran_order:
        return flat.reshape(shape[::-1]).transpose()
    return flat.reshape(shape)


@functools.lru_cache(maxsize=64)
def _npy_header(header: bytes) -> tuple[tuple[int, ...], bool, np.dtype, int] | None:
    """(shape, fortran_order, dtype, element count) of a whole ``.npy`` header (magic,
    length and dictionary) as NumPy parses it, None if NumPy refuses it or it describes an
    object array; remembered, since a client's answers repeat the same few headers."""
    fmt = np.lib.format
    stream = io.BytesIO(header)
    try:
        version = fmt.read_magic(stream)
        read = fmt.read_array_header_1_0 if version == (1, 0) else fmt.read_array_header_2_0
        shape, fortran_order, dtype = read(stream)
    except _HEADER_ERRORS:
        return None
    if dtype.hasobject or stream.read(1):
        return None
    count = 1
    for n in shape:
        count *= int(n)
    return tuple(int(n) for n in shape), bool(fortran_order), dtype, count


def _faces(faces: Any) -> np.ndarray:
    F = np.asarray(faces)
    if F.dtype.kind not in "iu":
        raise TypeError(f"faces must be integers, got dtype {F.dtype}")
    return F.astype(np.int32) if F.size == 0 or F.max() < 2**31 else F.astype(np.int64)


def _vertices(vertices: Any) -> np.ndarray:
    V = np.asarray(vertices)
    return V if V.dtype.kind == "f" else V.astype(np.float64)


def mesh_arrays(mesh: Any = None, *, vertices: Any = None, faces: Any = None, uv: Any = None,
                **extra: Any) -> dict[str, np.ndarray]:
    """The arrays of a mesh: ``vertices`` (V,3) float, ``faces`` (T,3) int32, ``uv`` (V,2)
    when known, and any ``extra`` arrays (e.g. ``uv_faces`` (T,3), ``region_<name>`` (V,)).

    Parameters
    ----------
    mesh : trimesh-like or mapping, optional   ``.vertices``, ``.faces``, ``.visual.uv``
    vertices, faces, uv : array_like, optional  given directly (override ``mesh``'s)
    """
    out: dict[str, Any] = {}
    if mesh is not None:
        if isinstance(mesh, Mapping):
            out.update({k: v for k, v in mesh.items() if v is not None})
        else:
            if not (hasattr(mesh, "vertices") and hasattr(mesh, "faces")):
                raise TypeError(f"a mesh needs .vertices and .faces, got {type(mesh).__name__}")
            out["vertices"], out["faces"] = mesh.vertices, mesh.faces
            visual_uv = getattr(getattr(mesh, "visual", None), "uv", None)
            if visual_uv is not None:
                out["uv"] = visual_uv
    for name, value in (("vertices", vertices), ("faces", faces), ("uv", uv), *extra.items()):
        if value is not None:
            out[name] = value
    if "vertices" not in out:
        raise TypeError("a mesh needs vertices (V,3)")
    out["vertices"] = _vertices(out["vertices"])
    if "faces" in out:
        out["faces"] = _faces(out["faces"])
    if "uv_faces" in out:
        out["uv_faces"] = _faces(out["uv_faces"])
    return {k: np.asarray(v) for k, v in out.items()}


def mesh_body(source: Any = None, **arrays: Any) -> tuple[bytes, str]:
    """A mesh upload's body and media type: a file's bytes as they are (``.obj``:
    ``model/obj``, ``.npz``: ``application/x-npz``), else the mesh's arrays as NPZ."""
    if is_path(source):
        path = Path(source)
        suffix = path.suffix.lower()
        if suffix not in (".obj", ".npz"):
            raise ValueError(f"{path}: a mesh file must be .obj or .npz")
        return path.read_bytes(), (OBJ if suffix == ".obj" else NPZ)
    if isinstance(source, (bytes, bytearray, memoryview)):
        data = bytes(source)
        return data, (NPZ if data[:2] == b"PK" else OBJ)
    return npz_bytes(**mesh_arrays(source, **arrays)), NPZ


def frames_array(frames: Any, what: str = "vertices") -> np.ndarray:
    """(F,N,3) from an (F,N,3) or one-frame (N,3) array, or a sequence of meshes (their
    ``.vertices``)."""
    if isinstance(frames, Sequence) and frames and hasattr(frames[0], "vertices"):
        frames = np.stack([np.asarray(m.vertices) for m in frames])
    elif hasattr(frames, "vertices") and not isinstance(frames, np.ndarray):
        frames = np.asarray(frames.vertices)
    array = np.asarray(frames)
    if array.ndim == 2:
        array = array[None]
    if array.ndim != 3 or array.shape[-1] != 3:
        raise ValueError(f"{what} must be (F,N,3) or (N,3), got shape {array.shape}")
    return array if array.dtype.kind == "f" else array.astype(np.float64)
