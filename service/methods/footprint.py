"""Memory held by a loaded model: what the service's model cache weighs models by.

A model's files say little about its size in memory: a shape-space model also holds the
prefactored Poisson and curvature-flow solves, a PDM its sampling operators. :func:`nbytes`
walks a model's attributes and adds up what actually occupies memory — NumPy arrays,
SciPy sparse matrices, sparse LU factors — counting each object once.

Arrays over a read-only file mapping (:func:`service.io.npz.npz_mapped`) are page cache:
their pages come in as they are read, are shared by every process that maps the same
file, and the kernel drops them again under memory pressure. A kind that reads all of
them on every frame (the PDM's coefficient maps) counts them; one that reads a few
frames of a large mapped database per request (shape space: the K active frames of N,
bermano2014 §5.4) does not (``Kind.weighs_mapped``). A mapped array that no frame reads at
all (the PDM's stored coefficient maps and strain band, whose copies in the evaluator's
texel order synthesis reads) costs no resident memory: its dataclass field says so with
``metadata=UNREAD`` and it is not counted while mapped (a dataclass-valued field: while
every array of it is mapped). A
mapped copy of an array that another field holds, laid out for one path, where a frame
reads one of the two and never both (the thin-shell basis: in vertex order for the marker
regression's mesh, reordered for the compiled medium band's) is counted once, under the
other field: ``metadata=COPY``.
"""

from __future__ import annotations

import dataclasses
import mmap
from typing import Any

import numpy as np
import scipy.sparse as sp

from service.geometry.sparse_solve import Factor

#: bytes per stored entry of a SuperLU factor (float64 value + int32 row index)
FACTOR_ENTRY_BYTES = 12
#: dataclass field metadata of an array no synthesized frame reads: not counted while it
#: lies over a file mapping (its pages are never touched), counted as usual otherwise
UNREAD = {"footprint": "unread"}
#: dataclass field metadata of an array laid out again from one another field holds, where a
#: frame reads either, never both: not counted while it lies over a file mapping
COPY = {"footprint": "copy"}
#: nesting depth followed into attributes, containers and their items (a served PDM: the
#: stream's unit check → model → evaluator → validity → texel operators → CSR → arrays)
MAX_DEPTH = 8


def file_mapped(array: np.ndarray) -> bool:
    """Whether ``array`` (or the array it views) lies over a memory-mapped file."""
    base = array
    while isinstance(base, np.ndarray) and base.base is not None:
        base = base.base
    if isinstance(base, memoryview):
        base = base.obj
    return isinstance(base, mmap.mmap)


def _counted(holder: Any, field: dataclasses.Field) -> Any:
    """The value of ``holder``'s dataclass ``field`` as :func:`nbytes` weighs it: None for
    a file-mapped array its field marks :data:`UNREAD` or :data:`COPY`, or such a dataclass
    whose arrays all lie over a file mapping (a stored object no frame reads)."""
    value = getattr(holder, field.name, None)
    if field.metadata.get("footprint") not in (UNREAD["footprint"], COPY["footprint"]):
        return value
    if isinstance(value, np.ndarray):
        return None if file_mapped(value) else value
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        arrays = [a for f in dataclasses.fields(value) if isinstance(a := getattr(value, f.name), np.ndarray)]
        return None if arrays and all(file_mapped(a) for a in arrays) else value
    return value


def nbytes(obj: Any, mapped: bool = True) -> int:
    """Bytes of the arrays, sparse matrices and factorizations reachable from ``obj``.

    Follows dataclass fields, ``__dict__`` attributes, and the items of lists, tuples,
    dicts (up to :data:`MAX_DEPTH` levels); a NumPy view counts its base array once.
    Python scalars, strings and small bookkeeping are not counted. ``mapped=False`` leaves
    out arrays over a memory-mapped file (:func:`file_mapped`).
    """
    seen: set[int] = set()

    def walk(x: Any, depth: int) -> int:
        if x is None or isinstance(x, (str, bytes, int, float, bool, np.generic)) or depth > MAX_DEPTH:
            return 0
        if isinstance(x, np.ndarray):
            base = x
            while isinstance(base.base, np.ndarray):
                base = base.base
            if id(base) in seen:
                return 0
            seen.add(id(base))
            return int(base.nbytes) if mapped or not file_mapped(base) else 0
        if id(x) in seen:
            return 0
        seen.add(id(x))
        if sp.issparse(x):
            return sum(walk(getattr(x, a, None), depth + 1) for a in ("data", "indices", "indptr", "row", "col", "offsets"))
        if isinstance(x, Factor):
            return FACTOR_ENTRY_BYTES * int(x.fill) + 8 * int(x.n)
        if isinstance(x, dict):
            return sum(walk(v, depth + 1) for v in x.values())
        if isinstance(x, (list, tuple, set, frozenset)):
            return sum(walk(v, depth + 1) for v in x)
        if dataclasses.is_dataclass(x) and not isinstance(x, type):
            return sum(walk(_counted(x, f), depth + 1) for f in dataclasses.fields(x))
        attrs = getattr(x, "__dict__", None)
        if attrs is not None:
            return sum(walk(v, depth + 1) for v in attrs.values())
        return 0

    return walk(obj, 0)
