"""service.io.npz: headers of untrusted .npz members (issue 16, defect 9)."""

from __future__ import annotations

import io
import zipfile

import numpy as np
import pytest

from service.io.mesh import MeshFormatError, read_npz
from service.io.npz import ZIP_ERRORS, npy_header, npz_arrays, npz_bytes


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
        read_npz(data)


def test_a_good_header_reads_back():
    data = npz_bytes(vertices=np.zeros((4, 3), np.float32))
    with zipfile.ZipFile(io.BytesIO(data)) as archive:
        assert npy_header(archive, "vertices.npy") == ((4, 3), np.dtype(np.float32))
