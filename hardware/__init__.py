"""Instrument layer: typed Protocols per hardware role, real drivers, the simulated instrument."""
