"""Seeded corruption of file bytes for the I/O readers' robustness tests."""

from __future__ import annotations

import numpy as np


def corrupt(data: bytes, rng: np.random.Generator, trial: int, plausible: bytes) -> bytes:
    """Truncate, overwrite a few bytes, or insert one of the ``plausible`` characters, by turns."""
    data = bytearray(data)
    if trial % 3 == 0:
        return bytes(data[: rng.integers(0, len(data))])
    if trial % 3 == 1:
        for _ in range(rng.integers(1, 4)):
            data[rng.integers(0, len(data))] = rng.integers(0, 256)
        return bytes(data)
    at = rng.integers(0, len(data))
    return bytes(data[:at] + bytes([rng.choice(list(plausible))]) + data[at:])
