"""The application layer: CLI, acquisition server, storage. Ties `merge` and `hardware` together."""
