"""Checks of named arrays, declared once: dtype kinds, shapes with named axes, finite values,
index ranges.

One dialect for every place that validates arrays from outside: the mesh type
(:mod:`service.io.triangle_mesh`), the mesh NPZ reader (:mod:`service.io.mesh_npz`), the actor
store's canonical writers (:mod:`service.store.actors`) and the upload parser
(:mod:`service.app.uploads`, which checks NPZ headers before any data is read). Each check has
one message form, naming the array, what was wrong and what was expected:

=========  ==============================================================================
dtype      ``'faces' has dtype float64, expected integers``
shape      ``'vertices' has shape (36, 2), expected (V, 3)``
axes       ``'markers' has 40 frames (axis 0) but 'vertices' has 41 (axis 0)``
finite     ``clip frame 2 vertex 5 has a non-finite coordinate (3 such entries in all)``
range      ``face 1 references vertex 4 but the mesh has 4 vertices (indices are 0-based)``
=========  ==============================================================================

Every check takes the error class to raise: :class:`~service.errors.InvalidInput` (422) by
default; the file readers pass their :class:`~service.io.errors.FormatError` subclass.

The shape and dtype checks work from ``(shape, dtype)`` alone, so an NPZ member is checked from
its ``.npy`` header before anything is allocated; the value checks (:func:`check_finite`) take
an array in memory or one still in a file (anything with a ``blocks(max_bytes)`` method, e.g.
:class:`service.io.npz.NpyMember`) and read it in blocks along axis 0, so checking a body of
hundreds of MiB holds one block of it at a time.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Iterator, Mapping, Sequence

import numpy as np

from service.errors import InvalidInput

#: names of the symbolic axes, for messages (``'uv' has 5 uv coordinates (axis 0) ...``)
AXES = {"F": "frames", "V": "vertices", "M": "markers", "T": "triangles",
        "K": "uv coordinates", "H": "texels per side", "A": "texels per side", "W": "texels",
        "P": "pairs", "N": "points", "O": "points"}

#: dtype kinds (numpy ``dtype.kind`` letters) → how messages say them
KINDS = {"f": "floating point", "iu": "integers", "fiu": "real numbers", "b": "bool",
         "biu": "bool or integers"}

#: the finite check's note for marker positions, where NaN is allowed (:func:`check_finite`)
OCCLUDED_NOTE = "; NaN marks an occluded marker, infinity is not allowed"

#: bytes of one block when values are checked or copied a block at a time
BLOCK_BYTES = 1 << 20

Dims = Sequence["str | int"]


def kinds_text(kinds: str) -> str:
    """How a message names the dtype kinds ``kinds`` (``"iu"`` → ``"integers"``)."""
    names = {"f": "floating point", "i": "integers", "u": "unsigned integers", "b": "bool"}
    return KINDS.get(kinds) or " or ".join(names[k] for k in kinds)


def describe(dims: Dims, lengths: Mapping[str, int] | None = None) -> str:
    """A shape pattern as messages write it: ``(F, V, 3)``; symbols with a known length in
    ``lengths`` are written as that length (``(2, M, 3)``)."""
    lengths = lengths or {}
    parts = [str(lengths.get(d, d)) if isinstance(d, str) else str(d) for d in dims]
    return "(" + ", ".join(parts) + (",)" if len(parts) == 1 else ")")


# ---------------------------------------------------------------------------- header checks
def check_dtype(name: str, dtype: np.dtype, kinds: str, error: type[Exception] = InvalidInput,
                note: str = "") -> None:
    """Refuse a dtype whose kind is not in ``kinds`` (``"f"``, ``"iu"``, ``"fiu"``, ...).

    Raises ``error("'faces' has dtype float64, expected integers" + note)``.
    """
    dtype = np.dtype(dtype)
    if dtype.kind not in kinds:
        raise error(f"{name} has dtype {dtype}, expected {kinds_text(kinds)}{note}")


class Axes:
    """The lengths of named axes shared by several arrays (``F`` frames, ``V`` vertices, ...),
    fixed by the first array that has them (or given up front).

    Parameters
    ----------
    **known : int   lengths the arrays must have (``Axes(F=2)``)
    """

    def __init__(self, **known: int):
        self.lengths: dict[str, int] = dict(known)
        self._owner: dict[str, tuple[str, int]] = {}

    def get(self, symbol: str, default: Any = None) -> Any:
        return self.lengths.get(symbol, default)

    def __getitem__(self, symbol: str) -> int:
        return self.lengths[symbol]

    def __contains__(self, symbol: str) -> bool:
        return symbol in self.lengths

    def check(self, name: str, shape: Sequence[int], dims: Dims,
              error: type[Exception] = InvalidInput) -> tuple[int, ...]:
        """Refuse ``shape`` unless it matches ``dims`` (an int: that exact length; a symbol:
        the same length in every array that has it); returns the shape as a tuple.

        Raises
        ------
        error   wrong rank or fixed length: ``'faces' has shape (2, 2), expected (T, 3)``;
                a length given up front: ``clip markers has shape (1, 4, 3), expected
                (2, M, 3)``; two arrays that disagree on a symbol: ``'markers' has 40
                frames (axis 0) but 'vertices' has 41 (axis 0)``
        """
        shape = tuple(int(s) for s in shape)
        preset = {d: n for d, n in self.lengths.items() if d not in self._owner}
        if len(shape) != len(dims) or any(
                size != (dim if isinstance(dim, int) else preset.get(dim, size))
                for size, dim in zip(shape, dims)):
            raise error(f"{name} has shape {shape}, expected {describe(dims, preset)}")
        for axis, (size, dim) in enumerate(zip(shape, dims)):
            if isinstance(dim, int):
                continue
            if dim not in self.lengths:
                self.lengths[dim], self._owner[dim] = size, (name, axis)
            elif size != self.lengths[dim]:
                first, first_axis = self._owner[dim]
                raise error(f"{name} has {size} {AXES.get(dim, dim)} (axis {axis}) but "
                            f"{first} has {self.lengths[dim]} (axis {first_axis})")
        return shape


def check_shape(name: str, shape: Sequence[int], dims: Dims,
                error: type[Exception] = InvalidInput, **known: int) -> tuple[int, ...]:
    """:meth:`Axes.check` for one array on its own (``known``: lengths of its symbols)."""
    return Axes(**known).check(name, shape, dims, error)


@dataclass(frozen=True)
class ArraySpec:
    """What one named array must look like: its axes and dtype kinds.

    Attributes
    ----------
    dims : tuple        per axis an int (that exact length) or a symbol of :data:`AXES`;
                        arrays sharing a symbol must agree on its length (:class:`Axes`)
    kinds : str         allowed dtype kinds (``"f"`` float, ``"i"``/``"u"`` integer, ``"b"`` bool)
    required : bool
    """

    dims: tuple[str | int, ...]
    kinds: str = "fiu"
    required: bool = True

    def describe(self) -> str:
        return describe(self.dims)

    def check(self, name: str, shape: Sequence[int], dtype: np.dtype, axes: Axes | None = None,
              error: type[Exception] = InvalidInput) -> tuple[int, ...]:
        """Check a header (or an array's ``shape``/``dtype``): dtype first, then shape."""
        check_dtype(name, dtype, self.kinds, error)
        return (axes if axes is not None else Axes()).check(name, shape, self.dims, error)


def as_array(values: Any, name: str, dims: Dims, kinds: str, dtype: Any,
             error: type[Exception] = InvalidInput, axes: Axes | None = None) -> np.ndarray:
    """``values`` as a C-contiguous array of ``dtype`` after :func:`check_dtype` (``kinds``)
    and the shape check (``dims``, against ``axes``)."""
    array = np.asarray(values)
    ArraySpec(tuple(dims), kinds).check(name, array.shape, array.dtype, axes, error)
    return np.ascontiguousarray(array, dtype=dtype)


def checked(values: Any, name: str, dims: Dims, kinds: str = "fiu",
            error: type[Exception] = InvalidInput, axes: Axes | None = None) -> Any:
    """``values`` after the dtype and shape checks, as it is: an array in a file (an object
    with ``blocks``, ``shape`` and ``dtype``) stays in its file, anything else becomes an
    ``np.asarray`` (not copied, not cast)."""
    if not (hasattr(values, "blocks") and hasattr(values, "shape")):
        values = np.asarray(values)
    ArraySpec(tuple(dims), kinds).check(name, values.shape, values.dtype, axes, error)
    return values


# ---------------------------------------------------------------------------- value checks
def blocks(values: Any, max_bytes: int = BLOCK_BYTES) -> Iterator[tuple[int, np.ndarray]]:
    """``(first row, block)`` along axis 0 of an array in memory, or of an array still in a
    file (an object with ``blocks(max_bytes)``), each block at most about ``max_bytes``."""
    if hasattr(values, "blocks") and not isinstance(values, np.ndarray):
        yield from values.blocks(max_bytes)
        return
    array = np.asarray(values)
    if array.ndim == 0 or len(array) == 0:
        yield 0, array
        return
    row = max(array[0].nbytes, 1)
    step = max(1, max_bytes // row)
    for start in range(0, len(array), step):
        yield start, array[start:start + step]


def check_finite(values: Any, name: str, labels: Sequence[str], allow_nan: bool = False,
                 note: str = "", error: type[Exception] = InvalidInput) -> None:
    """Refuse non-finite values, naming the first offender by its leading indices.

    Parameters
    ----------
    values : array (or an array in a file, see :func:`blocks`)
    name : str             the array's owner in messages, e.g. ``"clip"`` (may be ``""``)
    labels : str per axis  what the leading axes index, e.g. ``("frame", "vertex")``; the
                           remaining axes are the coordinates of one entry
    allow_nan : bool       NaN is allowed (an occluded marker), infinity is not
    note : str             appended inside the parentheses (``"; NaN marks ..."``)

    Raises ``error("clip frame 2 vertex 5 has a non-finite coordinate (3 such entries in
    all)")`` — "coordinate" when one axis is left, "value" otherwise.
    """
    if isinstance(values, np.ndarray) and (not np.isinf(values).any() if allow_nan
                                           else np.isfinite(values).all()):
        return                                # the usual case, in one pass and no mask
    lead = len(labels)
    count, first, ndim = 0, None, lead
    for start, block in blocks(values):
        ndim = block.ndim
        if block.size == 0:
            continue
        bad = np.isinf(block) if allow_nan else ~np.isfinite(block)
        if block.ndim > lead:
            bad = bad.reshape(bad.shape[:lead] + (-1,)).any(axis=-1)
        found = int(np.count_nonzero(bad))
        if found and first is None:
            index = np.unravel_index(int(np.argmax(bad)), bad.shape)
            first = (int(index[0]) + start,) + tuple(int(i) for i in index[1:])
        count += found
    if first is None:
        return
    where = " ".join(f"{label} {i}" for label, i in zip(labels, first))
    word = "coordinate" if ndim - lead == 1 else "value"
    raise error(f"{name} {where}".strip() + f" has a non-finite {word} ({count} such "
                f"entries in all{note})")


def check_indices(indices: np.ndarray, bound: int, row: str, element: str, owner: str,
                  plural: str, error: type[Exception] = InvalidInput,
                  skip: int | None = None) -> None:
    """Refuse an index outside ``[0, bound)``, naming the row that holds it.

    Parameters
    ----------
    indices : (R,) or (R,k) int   e.g. triangles (R,3) of vertex indices
    bound : int                   how many ``plural`` there are
    row, element : str            what a row is and what it indexes (``"face"``, ``"vertex"``)
    owner, plural : str           whose elements (``"mesh"``) and their plural (``"vertices"``)
    skip : int                    a value allowed besides the range (``NO_UV``: no uv)

    Raises ``error("face 1 references vertex 4 but the mesh has 4 vertices (indices are
    0-based)")``.
    """
    table = np.asarray(indices).reshape(len(indices), -1)
    outside = (table < 0) | (table >= bound)
    if skip is not None:
        outside &= table != skip
    bad = np.flatnonzero(outside.any(axis=1))
    if len(bad):
        r = int(bad[0])
        index = int(table[r][outside[r]][0])
        raise error(f"{row} {r} references {element} {index} but the {owner} has {bound} "
                    f"{plural} (indices are 0-based)")
