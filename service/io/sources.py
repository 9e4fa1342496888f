"""Where the readers get their bytes and the writers put theirs: paths, bytes or file objects.

Every reader of :mod:`service.io` takes a :data:`Source` (a path, bytes or a binary file
object) and every writer a :data:`Target` (a path or a binary file object); these two helpers
are the one place that turns them into bytes and back.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import BinaryIO, Union

Source = Union[str, os.PathLike, bytes, bytearray, memoryview, BinaryIO]
"""What a reader accepts: a path, the file's bytes, or a binary file object opened for reading."""
Target = Union[str, os.PathLike, BinaryIO]
"""What a writer accepts: a path, or a binary file object opened for writing."""


def is_path(value) -> bool:
    """Whether a source or target is a filesystem path (``str`` or ``os.PathLike``)."""
    return isinstance(value, (str, os.PathLike))


def read_source(source: Source) -> bytes:
    """The whole content of ``source``: a path is read, bytes are copied, a stream is read to its end."""
    if isinstance(source, (bytes, bytearray, memoryview)):
        return bytes(source)
    if is_path(source):
        return Path(source).read_bytes()
    return source.read()


def write_target(target: Target, data: bytes) -> None:
    """Write ``data`` to ``target``: a path is (over)written, a stream gets ``data`` appended."""
    if is_path(target):
        Path(target).write_bytes(data)
    else:
        target.write(data)
