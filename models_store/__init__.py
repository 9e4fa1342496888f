"""Model registry: SQL metadata and checksummed blobs.

- :mod:`models_store.ids`         prefixed, sortable ids and their validation
- :mod:`models_store.schema`      the SQLAlchemy tables (actors, clips, input rigs, models, jobs,
  artifacts)
- :mod:`models_store.db`          engines, sessions and migrations (:func:`models_store.db.upgrade`)
- :mod:`models_store.blobs`       the atomic, checksummed blob store on a local directory
- :mod:`models_store.cache`       a byte-budgeted LRU cache of loaded models
- :mod:`models_store.registry`    the operations the API and the jobs call
- :mod:`models_store.errors`      ``FacesynthError`` (the server's error root) → ``NotFound``, ``Conflict``, ``BlobCorrupt``,
  ``InvalidId``
"""
