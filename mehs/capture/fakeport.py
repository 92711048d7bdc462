"""A scripted pyserial stand-in for byte-exact protocol tests (PyMeasure ``expected_protocol`` style).

>>> port = ExpectedPort([(b"/1 1 get pos\\n", b"@01 1 OK IDLE -- 1000\\r\\n")])
>>> # driver writes must match exactly; each reply is then readable
>>> port.assert_done()   # fails if a scripted write was never made or a reply was never read

``(write, None)`` expects a write with no reply (the driver must then time
out); ``(None, reply)`` queues a reply without a write; a reply equal to
:data:`DISCONNECT` makes the next read fail as a vanished device does.
"""

from __future__ import annotations

from typing import Sequence

DISCONNECT = object()


class ProtocolMismatch(AssertionError):
    """The driver wrote something other than the script expected."""


class ExpectedPort:
    """pyserial-like port replaying ``pairs`` of (expected write, reply)."""

    def __init__(self, pairs: Sequence[tuple[bytes | None, object]], name: str = "fake://port"):
        self.pairs = list(pairs)
        self.pos = 0
        self.buffer = bytearray()
        self.disconnected = False
        self.name = name
        self.is_open = True
        self.writes: list[bytes] = []
        self._queue_unsolicited()

    def _queue_unsolicited(self) -> None:
        while self.pos < len(self.pairs) and self.pairs[self.pos][0] is None:
            self._queue(self.pairs[self.pos][1])
            self.pos += 1

    def _queue(self, reply) -> None:
        if reply is DISCONNECT:
            self.disconnected = True
        elif reply is not None:
            self.buffer += reply

    # pyserial API -------------------------------------------------------
    def write(self, data: bytes) -> int:
        data = bytes(data)
        self.writes.append(data)
        if self.pos >= len(self.pairs):
            raise ProtocolMismatch(f"unexpected write {data!r} (script exhausted)")
        expected, reply = self.pairs[self.pos]
        if data != expected:
            raise ProtocolMismatch(f"write #{self.pos}: expected {expected!r}, got {data!r}")
        self.pos += 1
        self._queue(reply)
        self._queue_unsolicited()
        return len(data)

    def flush(self) -> None:
        pass

    def _check_alive(self) -> None:
        if self.disconnected and not self.buffer:
            import serial

            raise serial.SerialException("socket disconnected")

    def read_until(self, expected: bytes = b"\n", size: int | None = None) -> bytes:
        self._check_alive()
        i = self.buffer.find(expected)
        n = len(self.buffer) if i < 0 else i + len(expected)
        out = bytes(self.buffer[:n])
        del self.buffer[:n]
        return out

    def read(self, size: int = 1) -> bytes:
        self._check_alive()
        out = bytes(self.buffer[:size])
        del self.buffer[:size]
        return out

    @property
    def in_waiting(self) -> int:
        return len(self.buffer)

    def reset_input_buffer(self) -> None:
        self.buffer.clear()

    def close(self) -> None:
        self.is_open = False

    # checks -------------------------------------------------------------
    def assert_done(self) -> None:
        if self.pos < len(self.pairs):
            raise ProtocolMismatch(f"expected write {self.pairs[self.pos][0]!r} was never made")
        if self.buffer:
            raise ProtocolMismatch(f"reply bytes never read: {bytes(self.buffer)!r}")
