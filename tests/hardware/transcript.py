"""A scripted serial link for transcript tests: (sent, reply) pairs, in order."""

from __future__ import annotations


class Transcript:
    """Plays the controller's side of a conversation and checks what the driver sends.

    ``pairs`` holds (expected bytes sent, reply bytes); a reply of ``b""`` is a time-out.
    """

    def __init__(self, pairs: list[tuple[bytes, bytes]]) -> None:
        self.pairs = list(pairs)
        self.sent: list[bytes] = []
        self._pending: list[bytes] = []
        self.closed = False
        self.flushed = 0

    def write(self, data: bytes) -> int:
        if not self.pairs:
            raise AssertionError(f"unexpected command {data!r}: the transcript is over")
        expected, reply = self.pairs.pop(0)
        if data != expected:
            raise AssertionError(f"sent {data!r}, expected {expected!r}")
        self.sent.append(data)
        self._pending.append(reply)
        return len(data)

    def readline(self) -> bytes:
        return self._pending.pop(0) if self._pending else b""

    def reset_input_buffer(self) -> None:
        self.flushed += 1

    def close(self) -> None:
        self.closed = True

    def done(self) -> bool:
        return not self.pairs
