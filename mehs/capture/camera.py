"""Line-scan camera driver: an SCPI-like ASCII protocol with binary line transfer.

The grammar is specified in ``docs/protocols.md`` ("mehs line-scan camera
protocol"); in short, every command line (``\\n``-terminated) gets exactly one
reply line: a value for queries, ``OK`` for settings and actions, or
``ERR <code>,"<message>"``. A line of data comes as an IEEE 488.2
definite-length block followed by a CRC-32::

    #<n><len><payload> <CRC32 as 8 upper-case hex digits>\\n

with ``payload`` = ``samples × bands`` little-endian uint16 in sample-major
order (the C-order ``(samples, bands)`` array, i.e. one BIP line).

Reliability: settings and queries are idempotent and retried after a
timeout, partial or garbled reply; a line whose CRC fails is transferred
again with ``FETC?`` (no new exposure); a lost ``READ?`` reply is retried
with a new ``READ?`` (the line is exposed again at the same stage position).
Before any retry the link is re-synchronised: the camera answers in order, so
after ``*IDN?`` everything it still owed (a line that came after the timeout)
arrives before the identification and is dropped — otherwise that late line
was read as the next line's and every later line was one behind, silently.
After a disconnect the driver reconnects and re-applies integration time
and shutter before anything else.
"""

from __future__ import annotations

import re
import time
import zlib
from typing import Any, Callable

import numpy as np

from mehs.capture.transport import Channel, SerialDriver
from mehs.errors import DeviceDisconnected, DeviceError, DeviceTimeout

_ERR_RE = re.compile(r'^ERR (?P<code>-?\d+),"(?P<msg>[^"]*)"$')
#: IEEE 488.2 ``*IDN?`` reply: manufacturer, model, serial, firmware
_IDN_RE = re.compile(r"^[^,]+,[^,]+,[^,]+,[^,]+$")
#: bytes a re-synchronisation may drop before it gives up (a few lines' worth)
_RESYNC_BYTES = 1 << 22


class CameraError(DeviceError):
    """The camera answered ``ERR <code>,"<message>"``."""

    def __init__(self, message: str, path=None, code: int = 0):
        super().__init__(message, path)
        self.code = code


class CameraProtocolError(DeviceError):
    """A reply that does not follow the protocol (garbled text, bad block, CRC mismatch)."""


def encode_block(payload: bytes) -> bytes:
    """``#<n><len><payload> <CRC32>\\n`` for ``payload``."""
    ln = str(len(payload)).encode("ascii")
    if len(ln) > 9:
        raise ValueError("block too long for a definite-length header")
    return (b"#" + str(len(ln)).encode("ascii") + ln + payload + b" "
            + f"{zlib.crc32(payload) & 0xFFFFFFFF:08X}".encode("ascii") + b"\n")


def encode_line(line: np.ndarray) -> bytes:
    """Block for a uint16 ``(samples, bands)`` line (little-endian, sample-major)."""
    return encode_block(np.ascontiguousarray(line, dtype="<u2").tobytes())


def _is_text(s: str) -> bool:
    return all(32 <= ord(c) < 127 for c in s)


class LineCamera(SerialDriver):
    """Driver for the line-scan camera protocol over a pyserial-like port.

    Parameters
    ----------
    port
        Open pyserial-like port.
    opener
        Callable re-opening the port after a disconnect.
    retries
        Attempts after a timeout, garbled reply or CRC failure.
    reconnects
        Reconnection attempts after a disconnect.
    """

    default_timeout = 2.0

    def __init__(self, port: Any, *, opener: Callable[[], Any] | None = None,
                 name: str | None = None, retries: int = 3, reconnects: int = 3,
                 retry_delay_s: float = 0.02):
        self.channel = Channel(port, opener=opener, name=name)
        self.retries, self.reconnects = int(retries), int(reconnects)
        self.retry_delay_s = float(retry_delay_s)
        self._shape: tuple[int, int] | None = None
        self._t_ms: float | None = None
        self._shutter_open: bool | None = None
        self._idn: str | None = None
        self.events: list[str] = []

    # ------------------------------------------------------------ low level
    def _reply_text(self, raw: bytes, command: str) -> str:
        text = raw.decode("ascii", "replace").rstrip("\r\n")
        if not _is_text(text):
            raise CameraProtocolError(f"garbled reply to {command!r}: {raw[:60]!r}", self.name)
        m = _ERR_RE.match(text)
        if m:
            raise CameraError(f"camera error {m['code']} on {command!r}: {m['msg']}", self.name,
                              code=int(m["code"]))
        return text

    def _once(self, command: str) -> str:
        self.channel.write(command.encode("ascii") + b"\n")
        return self._reply_text(self.channel.read_line(b"\n", what=f"reply to {command!r}"), command)

    def _retrying(self, what: str, fn: Callable[[], Any]) -> Any:
        last: DeviceError | None = None
        for attempt in range(self.retries + 1):
            try:
                return fn()
            except (DeviceTimeout, CameraProtocolError, DeviceDisconnected) as exc:
                last = exc
                self.events.append(f"camera: {type(exc).__name__} on {what!r}: {exc.problem}")
                if attempt < self.retries:
                    self._recover(exc)
        raise type(last)(f"{last.problem} (after {self.retries + 1} attempts of {what!r})", self.name)

    def query(self, command: str) -> str:
        """Send an idempotent command and return its reply text (retried on transient faults)."""
        return self._retrying(command, lambda: self._once(command))

    def command(self, command: str) -> None:
        """Send a setting/action and require ``OK``."""
        def go():
            r = self._once(command)
            if r != "OK":
                raise CameraProtocolError(f"expected OK to {command!r}, got {r!r}", self.name)
        self._retrying(command, go)

    def _number(self, command: str) -> float:
        def go():
            r = self._once(command)
            try:
                v = float(r)
            except ValueError:
                raise CameraProtocolError(f"reply to {command!r} is not a number: {r!r}", self.name) from None
            if not np.isfinite(v):
                raise CameraProtocolError(f"reply to {command!r} is not finite: {r!r}", self.name)
            return v
        return self._retrying(command, go)

    # ------------------------------------------------------------ settings
    def identify(self) -> str:
        self._idn = self.query("*IDN?")
        return self._idn

    # ------------------------------------------------------------ recovery
    def _recover(self, exc: DeviceError) -> None:
        """After a disconnect reconnect; otherwise drop stale bytes and re-synchronise
        (:meth:`_resync`), so that the retry reads its own reply."""
        super()._recover(exc)
        if isinstance(exc, DeviceDisconnected):
            return
        try:
            self._resync()
        except DeviceError as e:    # the retry will meet the fault again and recover again
            self.events.append(f"camera: re-synchronisation failed: {e.problem}")

    def _resync(self) -> None:
        """Send ``*IDN?`` and read up to its reply, dropping what comes before it.

        The camera answers commands in order, so replies it still owed when the host
        gave up — a late line block, an ``OK`` — come first; the rest of a reply cut
        by the discarded input comes as undecodable text. Both are dropped (and
        logged); then the link is in step again.
        """
        ch = self.channel
        ch.write(b"*IDN?\n")
        dropped = 0
        while dropped <= _RESYNC_BYTES:
            first = ch.read_exact(1, what="reply to *IDN? (re-synchronisation)")
            if first == b"#":
                try:
                    nd = int(ch.read_exact(1, what="block header"))
                    n = int(ch.read_exact(nd, what="block length")) if nd > 0 else -1
                except ValueError:
                    n = -1
                if 0 <= n <= _RESYNC_BYTES - dropped:
                    ch.read_exact(n + 10, what="late line data")
                    dropped += n + 12
                    self.events.append(f"camera: dropped a late line ({n} bytes) while "
                                       "re-synchronising")
                    continue
                raw = first + ch.read_line(b"\n", what="reply")
            else:
                raw = first + ch.read_line(b"\n", what="reply to *IDN? (re-synchronisation)")
            text = raw.decode("ascii", "replace").rstrip("\r\n")
            if (text == self._idn) if self._idn else (_is_text(text) and bool(_IDN_RE.match(text))):
                return
            dropped += len(raw)
            self.events.append(f"camera: dropped a late or broken reply {raw[:40]!r} while "
                               "re-synchronising")
        raise CameraProtocolError(f"no reply to *IDN? within {_RESYNC_BYTES} bytes while "
                                  "re-synchronising", self.name)

    def shape(self) -> tuple[int, int]:
        """``(samples, bands)`` of one line."""
        def go():
            r = self._once("FORM:SHAP?")
            try:
                s, b = (int(v) for v in r.split(","))
            except ValueError:
                raise CameraProtocolError(f"bad shape reply {r!r}", self.name) from None
            if s <= 0 or b <= 0:
                raise CameraProtocolError(f"bad shape reply {r!r}", self.name)
            return s, b
        self._shape = self._retrying("FORM:SHAP?", go)
        return self._shape

    def _floats(self, command: str) -> np.ndarray:
        def go():
            r = self._once(command)
            try:
                v = np.array([float(x) for x in r.split(",")])
            except ValueError:
                raise CameraProtocolError(f"bad list reply to {command!r}", self.name) from None
            return v
        return self._retrying(command, go)

    def wavelengths(self) -> np.ndarray:
        """Band centres (nm)."""
        return self._floats("SYST:WAV?")

    def fwhm(self) -> np.ndarray:
        return self._floats("SYST:FWHM?")

    def bit_depth(self) -> int:
        return int(self._number("SYST:BITS?"))

    def set_integration_time(self, ms: float) -> float:
        """Set the integration time; returns the actual time the camera uses (ms)."""
        self.command(f"CONF:INT {float(ms):.6g}")
        self._t_ms = self.integration_time()
        return self._t_ms

    def integration_time(self) -> float:
        return self._number("CONF:INT?")

    def set_shutter(self, open_: bool) -> None:
        self.command("SHUT OPEN" if open_ else "SHUT CLOSE")
        self._shutter_open = bool(open_)

    def shutter_open(self) -> bool:
        r = self.query("SHUT?")
        if r not in ("OPEN", "CLOSED"):
            raise CameraProtocolError(f"bad shutter state {r!r}", self.name)
        return r == "OPEN"

    def temperature(self) -> float:
        return self._number("TEMP?")

    def frame_rate(self) -> float:
        return self._number("FRAT?")

    def errors(self) -> list[str]:
        """Drain the error queue (``SYST:ERR?`` until ``0,...``)."""
        out = []
        for _ in range(64):
            r = self.query("SYST:ERR?")
            if r.startswith("0,"):
                break
            out.append(r)
        return out

    def reconnect(self) -> None:
        """Re-open the port and re-apply integration time and shutter."""
        last: DeviceError | None = None
        for attempt in range(self.reconnects):
            try:
                self.channel.reopen()
                if self._t_ms is not None:
                    self._once(f"CONF:INT {self._t_ms:.6g}")
                if self._shutter_open is not None:
                    self._once("SHUT OPEN" if self._shutter_open else "SHUT CLOSE")
                self.events.append("camera: reconnected, settings re-applied")
                return
            except DeviceError as exc:
                last = exc
                time.sleep(min(0.05 * 2 ** attempt, 1.0))
        raise DeviceDisconnected(f"could not reconnect after {self.reconnects} attempts "
                                 f"({last.problem if last else 'no attempt'})", self.name)

    # ------------------------------------------------------------ data
    def _read_block(self) -> bytes:
        ch = self.channel
        head = ch.read_exact(2, what="block header")
        if head[:1] != b"#":
            # an ERR reply (or garbage) instead of a block
            rest = ch.read_line(b"\n", what="reply")
            self._reply_text(head + rest, "READ?")
            raise CameraProtocolError(f"expected a block, got {(head + rest)[:60]!r}", self.name)
        try:
            nd = int(head[1:2])
            if nd < 1:
                raise ValueError
            n = int(ch.read_exact(nd, what="block length"))
        except ValueError:
            raise CameraProtocolError(f"bad block header {head!r}", self.name) from None
        if self._shape is not None and n != 2 * self._shape[0] * self._shape[1]:
            raise CameraProtocolError(f"block of {n} bytes, expected {2 * self._shape[0] * self._shape[1]}",
                                      self.name)
        payload = ch.read_exact(n, what="line data")
        tail = ch.read_exact(10, what="block CRC")
        if tail[:1] != b" " or tail[-1:] != b"\n":
            raise CameraProtocolError(f"bad block trailer {tail!r}", self.name)
        try:
            crc = int(tail[1:9], 16)
        except ValueError:
            raise CameraProtocolError(f"bad block CRC {tail!r}", self.name) from None
        if zlib.crc32(payload) & 0xFFFFFFFF != crc:
            raise CameraProtocolError("line data CRC mismatch (corrupted transfer)", self.name)
        return payload

    def read_line(self) -> np.ndarray:
        """Expose and read one line: uint16 ``(samples, bands)``.

        A CRC failure re-transfers the same exposure (``FETC?``); a timeout or a
        disconnect exposes the line again (``READ?``) after recovery.
        """
        if self._shape is None:
            self.shape()
        samples, bands = self._shape
        command = "READ?"
        last: DeviceError | None = None
        for attempt in range(self.retries + 1):
            try:
                self.channel.write(command.encode("ascii") + b"\n")
                payload = self._read_block()
                return np.frombuffer(payload, dtype="<u2").reshape(samples, bands).astype(np.uint16)
            except (DeviceTimeout, CameraProtocolError, DeviceDisconnected) as exc:
                last = exc
                self.events.append(f"camera: {type(exc).__name__} on {command!r}: {exc.problem}")
                if attempt >= self.retries:
                    break
                self._recover(exc)
                # only a transfer that arrived corrupted can be fetched again
                command = "FETC?" if isinstance(exc, CameraProtocolError) else "READ?"
        raise type(last)(f"{last.problem} (after {self.retries + 1} attempts to read a line)", self.name)
