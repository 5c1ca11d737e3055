"""Typed errors of a SharkSEM link: every failure an operator can act on."""

from __future__ import annotations


class SharkSEMError(Exception):
    """Any failure of the link to a TESCAN SEM or of a command it carried."""


class SharkSEMLinkError(SharkSEMError):
    """The link could not be opened, or dropped (network, the SEM's software closed)."""


class SharkSEMTimeout(SharkSEMError):
    """The SEM did not answer, or stopped streaming an image, within the time-out."""


class SharkSEMProtocolError(SharkSEMError):
    """A message that does not follow the wire format (short, garbled, another command's)."""
