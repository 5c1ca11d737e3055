"""Typed errors of a SmarAct MCS controller link: every failure an operator can act on."""

from __future__ import annotations

#: Error codes of the MCS ASCII interface and what they mean (vendor numbering).
ERROR_MEANINGS: dict[int, str] = {
    1: "syntax error",
    2: "invalid command",
    3: "overflow",
    4: "parse error",
    5: "too few parameters",
    6: "too many parameters",
    7: "invalid parameter",
    8: "wrong communication mode",
    129: "no sensor present",
    140: "sensor disabled",
    141: "command overridden",
    142: "end stop reached",
    143: "wrong sensor type",
    144: "could not find reference mark",
    145: "wrong end effector type",
    146: "movement locked",
    147: "range limit reached",
    148: "physical position unknown",
    150: "command not processed",
    151: "waiting for trigger",
    152: "command queue full",
}


class MCSError(Exception):
    """Any failure of an MCS link or controller."""


class MCSLinkError(MCSError):
    """The link could not be opened, or dropped (cable, network, controller off)."""


class MCSTimeout(MCSError):
    """The controller did not answer within the time-out."""


class MCSProtocolError(MCSError):
    """The controller answered something that is not a valid reply to the command."""


class MCSControllerError(MCSError):
    """The controller refused a command with an error code.

    Attributes
    ----------
    code : int
        The controller's error code (see :data:`ERROR_MEANINGS`).
    channel : int
        The channel it refers to; -1 for the system.
    meaning : str
        What the code means.
    """

    def __init__(self, code: int, channel: int, command: str = "") -> None:
        self.code = code
        self.channel = channel
        self.meaning = ERROR_MEANINGS.get(code, "unknown error")
        where = "system" if channel < 0 else f"channel {channel}"
        sent = f" (command {command!r})" if command else ""
        super().__init__(f"MCS error {code} on {where}: {self.meaning}{sent}")


class MCSCommandError(MCSControllerError):
    """Codes 1-8: the controller did not understand the command (a software bug)."""


class NoSensorError(MCSControllerError):
    """Code 129: the channel has no position sensor; closed-loop moves are impossible."""


class EndStopError(MCSControllerError):
    """Code 142: the positioner ran into its mechanical end stop."""


class RangeLimitError(MCSControllerError):
    """Code 147: the target lies outside the channel's (soft) range limit."""


class PositionUnknownError(MCSControllerError):
    """Code 148: the physical position is unknown (reference not found)."""


_BY_CODE: dict[int, type[MCSControllerError]] = {
    **dict.fromkeys(range(1, 9), MCSCommandError),
    129: NoSensorError,
    142: EndStopError,
    147: RangeLimitError,
    148: PositionUnknownError,
}


def controller_error(code: int, channel: int, command: str = "") -> MCSControllerError:
    """The typed exception for an error reply ``:E<channel>,<code>``."""
    return _BY_CODE.get(code, MCSControllerError)(code, channel, command)
