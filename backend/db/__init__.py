"""Storage: SQLAlchemy models on SQLite (schema only through Alembic) and the HDF5 patch store."""
