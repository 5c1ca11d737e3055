"""A Nanonis (SPECS) SPM controller over its TCP programming interface.

The wire format (:mod:`hardware.nanonis.wire`) is the contract: a 40-byte big-endian header
(command name, body size, response flag), a typed body, and in every response an error block.
:mod:`hardware.nanonis.client` speaks it over a socket; :mod:`hardware.nanonis.roles` and
:mod:`hardware.nanonis.scanner` fill the instrument's role Protocols with it (probe signal on
the PLL, force loop on the Z controller, Z and scan piezos, coarse motors, frame scans). The
simulator that answers the same bytes is :mod:`hardware.sim.nanonis_server`.
"""
