"""File formats, one module per format family.

- meshes: :mod:`~service.io.mesh` (the public mesh API and :func:`read_mesh` by suffix) over
  :mod:`~service.io.triangle_mesh` (the :class:`Mesh` type and its validation),
  :mod:`~service.io.obj`, :mod:`~service.io.ply`, :mod:`~service.io.mesh_npz`;
- markers: :mod:`~service.io.markers` (the public marker API and :func:`read_markers` by suffix)
  over :mod:`~service.io.marker_sequence`, :mod:`~service.io.marker_json` (frames and the
  layout), :mod:`~service.io.marker_csv`, :mod:`~service.io.trc`, :mod:`~service.io.c3d`;
- UV-space maps: :mod:`~service.io.exr`; a performance as one USD point cache: :mod:`~service.io.usd`;
- shared: :mod:`~service.io.sources` (paths, bytes or streams in and out),
  :mod:`~service.io.npz` (archive headers before data), :mod:`~service.io.errors`, and
  :mod:`~service.io.atomic` (re-exports :mod:`models_store.atomic`).
"""
