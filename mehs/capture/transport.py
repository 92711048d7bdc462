"""Byte transport for the device drivers: a pyserial port, checked for pyserial's pitfalls.

Drivers never open ports themselves; they receive a pyserial-like object
(``write``, ``read``, ``read_until``, ``reset_input_buffer``, ``close``) — a real
``/dev/ttyUSB0``, a pseudo-terminal, ``socket://127.0.0.1:PORT`` (the
simulators), or a scripted fake in tests (:mod:`mehs.capture.fakeport`).

pyserial pitfalls handled here (design §2.2):

- ``read_until`` returns whatever arrived when the timeout expires, without
  raising: every reply is checked for its terminator, and a short read is a
  :class:`~mehs.errors.DeviceTimeout` (nothing arrived) or a partial reply.
- A POSIX port that "reports readiness to read but returned no data", or a
  socket whose peer closed, means the device is gone: that is a
  :class:`~mehs.errors.DeviceDisconnected`, never a retryable timeout.
- Ports are opened with ``exclusive=True`` so a second program cannot
  interleave bytes with ours.
"""

from __future__ import annotations

import time
from typing import Any, Callable

from mehs.errors import DeviceDisconnected, DeviceError, DeviceTimeout, InputError


class PartialReply(DeviceTimeout):
    """Some bytes arrived but not the terminator before the timeout."""


def open_port(url: str, *, timeout: float = 2.0, baudrate: int = 115200,
              exclusive: bool = True) -> Any:
    """Open ``url`` with :func:`serial.serial_for_url` (``/dev/tty…``, ``socket://host:port``, ``loop://``).

    Raises
    ------
    DeviceDisconnected
        When the port cannot be opened (absent device, refused connection).
    """
    import serial

    if timeout is None or not (timeout > 0 and timeout != float("inf")):
        # pyserial's "Not a valid timeout" would read as a fault of the port
        raise InputError(f"reply timeout must be a positive number of seconds, got {timeout}")
    kwargs: dict[str, Any] = {"timeout": timeout, "write_timeout": timeout}
    if not url.startswith(("socket://", "loop://", "rfc2217://")):
        kwargs.update(baudrate=baudrate, exclusive=exclusive)
    try:
        port = serial.serial_for_url(url, **kwargs)
    except (serial.SerialException, OSError, ValueError) as exc:
        raise DeviceDisconnected(f"cannot open port ({exc})", url) from None
    sock = getattr(port, "_socket", None)
    if sock is not None:
        import socket

        # Small commands followed by a wait for the reply: Nagle's algorithm
        # plus delayed ACKs would add up to 40 ms per round trip.
        try:
            sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        except OSError:
            pass
    return port


def port_name(port: Any) -> str:
    return str(getattr(port, "name", None) or getattr(port, "port", None) or port)


class Channel:
    """A port plus the checks every driver needs; ``opener`` re-creates the port after a disconnect.

    Parameters
    ----------
    port
        An open pyserial-like object.
    opener
        Zero-argument callable returning a fresh port (``None``: reconnect impossible).
    name
        Used in error messages (the URL or device path).
    """

    def __init__(self, port: Any, *, opener: Callable[[], Any] | None = None,
                 name: str | None = None):
        self.port = port
        self.opener = opener
        self.name = name or port_name(port)

    # -- errors ---------------------------------------------------------
    def _wrap(self, exc: BaseException) -> DeviceError:
        text = str(exc)
        low = text.lower()
        if ("disconnect" in low or "returned no data" in low or "closed" in low
                or "broken pipe" in low or "not open" in low or "reset by peer" in low
                or isinstance(exc, (BrokenPipeError, ConnectionError))):
            return DeviceDisconnected(f"connection lost ({text})", self.name)
        return DeviceError(f"I/O error ({text})", self.name)

    def _io(self, fn, *args):
        import serial

        try:
            return fn(*args)
        except (serial.SerialException, OSError) as exc:
            raise self._wrap(exc) from None

    # -- bytes ----------------------------------------------------------
    def write(self, data: bytes) -> None:
        if self.port is None:
            raise DeviceDisconnected("not connected", self.name)
        self._io(self.port.write, data)
        flush = getattr(self.port, "flush", None)
        if flush is not None:
            self._io(flush)

    def read_line(self, terminator: bytes = b"\n", *, what: str = "reply") -> bytes:
        """One reply including ``terminator``; short reads raise (never a silent partial line)."""
        if self.port is None:
            raise DeviceDisconnected("not connected", self.name)
        data = self._io(self.port.read_until, terminator)
        if data.endswith(terminator):
            return data
        if not data:
            raise DeviceTimeout(f"no {what} before the timeout", self.name)
        raise PartialReply(f"partial {what} {data[:60]!r} (no terminator before the timeout)",
                           self.name)

    def read_exact(self, n: int, *, what: str = "data") -> bytes:
        if self.port is None:
            raise DeviceDisconnected("not connected", self.name)
        data = self._io(self.port.read, n)
        if len(data) != n:
            if not data:
                raise DeviceTimeout(f"no {what} before the timeout", self.name)
            raise PartialReply(f"{what}: got {len(data)} of {n} bytes before the timeout", self.name)
        return data

    def discard_input(self) -> None:
        """Drop stale bytes (e.g. the rest of a garbled reply) before a retry."""
        if self.port is None:
            return
        reset = getattr(self.port, "reset_input_buffer", None)
        if reset is not None:
            self._io(reset)

    # -- connection -----------------------------------------------------
    def close(self) -> None:
        if self.port is not None:
            sock = getattr(self.port, "_socket", None)
            if sock is not None:
                # pyserial's socket:// close() sleeps 0.3 s "for quick reconnects";
                # our servers need no grace period, so close the socket directly.
                import socket

                try:
                    sock.shutdown(socket.SHUT_RDWR)
                except OSError:
                    pass
                sock.close()
                self.port._socket = None
                self.port.is_open = False
                self.port = None
                return
            try:
                self.port.close()
            except Exception:  # noqa: BLE001 - closing a dead port may fail in many ways
                pass
            self.port = None

    def reopen(self) -> None:
        """Close and re-open through ``opener``; raises DeviceDisconnected if impossible."""
        if self.opener is None:
            raise DeviceDisconnected("connection lost and no way to reconnect was given", self.name)
        self.close()
        self.port = self.opener()


class SerialDriver:
    """What every device driver shares: a :class:`Channel`, opening by URL, closing.

    Subclasses set :attr:`default_timeout` (seconds) and build ``self.channel``
    in their ``__init__(port, *, opener=None, name=None, ...)``.
    """

    default_timeout: float = 1.0
    channel: Channel

    @classmethod
    def open(cls, url: str, *, timeout: float | None = None, **kwargs: Any):
        """Open ``url`` (``/dev/ttyUSB0``, ``socket://host:port``) and return a driver that can reconnect."""
        t = cls.default_timeout if timeout is None else timeout
        opener = lambda: open_port(url, timeout=t)  # noqa: E731
        return cls(opener(), opener=opener, name=url, **kwargs)

    @property
    def name(self) -> str:
        return self.channel.name

    def close(self) -> None:
        self.channel.close()

    def _recover(self, exc: DeviceError) -> None:
        """Make the link usable again after ``exc``: reconnect after a disconnect, else drop stale bytes.

        Subclasses provide ``reconnect()`` (which re-reads device state) and ``retry_delay_s``.
        """
        if isinstance(exc, DeviceDisconnected):
            self.reconnect()
        else:
            time.sleep(self.retry_delay_s)
            self.channel.discard_input()

    def __enter__(self):
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()
