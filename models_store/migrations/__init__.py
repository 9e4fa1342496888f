"""Alembic migrations of the metadata database; run them with :func:`models_store.db.upgrade`.

``versions/`` holds the committed revision scripts. A migration describes the schema as it
was when written (plain SQLAlchemy types, no imports from :mod:`models_store.schema`), so
later changes to the ORM classes never rewrite history.
"""
