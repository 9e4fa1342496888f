"""NPZ headers: hostile .npy headers are a ValueError the callers turn into a 422."""

import io
import zipfile

import numpy as np
import pytest

from service.io.errors import MeshFormatError
from service.io.mesh_npz import read_npz
from service.io.npz import ZIP_ERRORS, npy_header


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
