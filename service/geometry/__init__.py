"""The shared numerical core: plain functions over NumPy arrays and SciPy sparse matrices.

Conventions: ``V`` (n,3) float vertex positions (mm), ``F`` (m,3) int triangles,
sparse matrices in CSR/CSC from :mod:`scipy.sparse`. Nothing here re-indexes a mesh.
"""
