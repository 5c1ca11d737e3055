"""Acquisition: planning a mosaic, and the state machine of a run and of its patches."""
