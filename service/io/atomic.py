"""Atomic file writes for :mod:`service`: re-exported from :mod:`models_store.atomic`.

The helpers live in the lower ``models_store`` package (the blob store needs them and imports
nothing of ``service``); this module keeps ``service.io.atomic`` importable for the service's
writers.
"""

from models_store.atomic import atomic_open, sha256_file, write_bytes, write_npz

__all__ = ["atomic_open", "sha256_file", "write_bytes", "write_npz"]
