"""Errors raised by the file-format readers and writers of :mod:`service.io`.

Every reader raises a subclass of :class:`FormatError` (an :class:`~service.errors.InvalidInput`, so a ``ValueError``) for input it
cannot accept, with a message that names what is wrong and what was expected, e.g.
``"face 12 (line 40300) references vertex 40001 but the file has 40000 vertices"``. The API
maps :class:`SizeLimitError` to 413 and every other :class:`FormatError` to 422.
"""

from service.errors import InvalidInput, PayloadTooLarge


class FormatError(InvalidInput):
    """A file (or in-memory payload) is malformed or violates the format's contract."""


class MeshFormatError(FormatError):
    """A mesh file (OBJ, PLY, NPZ) or mesh arrays are malformed."""


class MapFormatError(FormatError):
    """A UV-space map file (EXR) is malformed or not of the expected layout."""


class MarkerFormatError(FormatError):
    """A marker file (JSON, CSV, TRC, C3D) or marker layout is malformed."""


class SizeLimitError(PayloadTooLarge, FormatError):
    """A file declares more elements (vertices, faces, texels, frames...) than allowed.

    Raised before anything proportional to the declared size is allocated.

    Attributes
    ----------
    what : str        what was counted, e.g. ``"vertices"``
    count : int       the count the file declares
    limit : int       the configured maximum
    """

    def __init__(self, what: str, count: int, limit: int):
        super().__init__(f"the file declares {count} {what}, more than the limit of {limit}")
        self.what = what
        self.count = count
        self.limit = limit
