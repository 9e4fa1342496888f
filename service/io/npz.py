"""Reading ``.npz`` archives that came from outside: array headers before any data.

Both the mesh reader and the API's upload parser decide from the headers (shape, dtype)
whether to read an array at all, so nothing is allocated for a declared size that breaks a
limit and no pickle is ever loaded. :func:`npz_arrays` and :func:`npz_bytes` are the plain
in-memory round trip for trusted data (stored models, results).
"""

from __future__ import annotations

import io
import struct
import tokenize
import zipfile
import zlib

import numpy as np

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
        version = np.lib.format.read_magic(f)
        if version not in ((1, 0), (2, 0)):
            raise ValueError(f"unsupported .npy format version {version}; expected 1.0 or 2.0")
        read = (np.lib.format.read_array_header_1_0 if version == (1, 0)
                else np.lib.format.read_array_header_2_0)
        try:
            shape, _, dtype = read(f)
        except _HEADER_ERRORS as error:
            # numpy tokenizes the header (a Python literal) before its own checks
            raise ValueError(f"malformed .npy header: {error}") from None
    if any(int(n) < 0 for n in shape):
        raise ValueError(f"malformed .npy header: negative dimension in shape {shape}")
    return tuple(int(s) for s in shape), dtype


def npz_arrays(data: bytes) -> dict[str, np.ndarray]:
    """Every array of an in-memory ``.npz`` (never unpickled); a malformed member header
    raises ``ValueError`` (see :func:`npy_header`)."""
    try:
        with np.load(io.BytesIO(data), allow_pickle=False) as d:
            return {k: d[k] for k in d.files}
    except _HEADER_ERRORS as error:
        raise ValueError(f"malformed .npy header: {type(error).__name__}") from None


def npz_bytes(**arrays: np.ndarray) -> bytes:
    """An uncompressed in-memory ``.npz`` of ``arrays``."""
    buffer = io.BytesIO()
    np.savez(buffer, **arrays)
    return buffer.getvalue()
