"""Instrument layer: hardware roles as typed Protocols, real drivers and the simulated instrument."""
