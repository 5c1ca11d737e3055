"""Typed errors of a Nanonis link: every failure an operator can act on."""

from __future__ import annotations


class NanonisError(Exception):
    """Any failure of the Nanonis link or of a command it carried."""


class NanonisLinkError(NanonisError):
    """The TCP link could not be opened, or dropped (network, controller software closed)."""


class NanonisTimeout(NanonisError):
    """The controller did not answer within the time-out."""


class NanonisProtocolError(NanonisError):
    """A reply that does not follow the wire format (short, garbled, another command's)."""


class NanonisCommandError(NanonisError):
    """The controller answered with its error block set: the command was refused."""

    def __init__(self, command: str, status: int, description: str) -> None:
        self.command = command
        self.status = status
        self.description = description
        super().__init__(f"{command} refused (error {status}): {description or 'no description'}")
