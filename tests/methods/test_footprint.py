"""Tests for service.methods.footprint.nbytes: the model cache's weight of a loaded model."""

from dataclasses import dataclass, field

import numpy as np
import scipy.sparse as sp

from service.geometry.sparse_solve import factorize
from service.methods.footprint import FACTOR_ENTRY_BYTES, nbytes


@dataclass
class Holder:
    a: np.ndarray
    view: np.ndarray
    parts: dict = field(default_factory=dict)
    other: object = None


class Plain:
    def __init__(self, x):
        self.x = x
        self.name = "plain"


def test_counts_arrays_once_sparse_and_factors():
    a = np.zeros((100, 10))                                    # 8000 bytes
    S = sp.identity(50, format="csr")                          # 50 values, 50 indices, 51 indptr
    F = factorize(sp.identity(20, format="csc") * 2.0)
    h = Holder(a=a, view=a[::2], parts={"s": S, "f": F, "again": a, "list": [np.ones(4, np.float32)]},
               other=Plain(np.arange(3, dtype=np.int64)))
    sparse = S.data.nbytes + S.indices.nbytes + S.indptr.nbytes
    assert nbytes(h) == 8000 + sparse + (FACTOR_ENTRY_BYTES * F.fill + 8 * 20) + 16 + 24
