"""Serve a line protocol's handler as a serial device would: loopback TCP or a pty.

A handler maps one received line (terminator included) to ``(reply, fault)``;
the servers apply the fault to the reply as a broken link would (``timeout``: no
reply, ``garble``: corrupted bytes, ``partial``: half a reply without its
terminator, ``disconnect``: the connection drops, ``late``: the reply is held back
past the host's timeout and sent just before the next one). The simulated Zaber stage and
line camera (:mod:`mehs.capture.simdevice`) and the GigE Vision simulator's stage
(:mod:`mehs.capture.genicam_sim`) are served this way, so the production drivers
open them through pyserial exactly as hardware.
"""

from __future__ import annotations

import os
import socket
import threading
from typing import Callable

from mehs.errors import DeviceError, InputError


def _corrupt(reply: bytes) -> bytes:
    """Flip bytes in the middle of a reply, keeping its length and terminator."""
    b = bytearray(reply)
    n = len(b)
    if n <= 2:
        return b"\xff" + bytes(b[1:])
    mid = max(1, n // 2)
    for i in range(mid, min(mid + 3, n - 1)):
        b[i] ^= 0x5A
    return bytes(b)


class DeviceServer:
    """Serve one protocol handler on a loopback TCP port, one client at a time (like a serial port)."""

    def __init__(self, handler: Callable[[bytes], tuple[bytes | None, str | None]], *,
                 host: str = "127.0.0.1", port: int = 0, name: str = "device"):
        self.handler, self.name = handler, name
        if not 0 <= int(port) <= 65535:  # socket.bind raises a bare OverflowError
            raise InputError(f"{name} port must be 0..65535 (0 = any free port), got {port}")
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        self.sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            self.sock.bind((host, port))
            self.sock.listen(4)
        except OSError as exc:
            self.sock.close()
            raise DeviceError(f"cannot serve the simulated {name} here ({exc.strerror or exc}); "
                              "choose another --port or 0", f"{host}:{port}") from None
        self.host, self.port = self.sock.getsockname()[:2]
        self._closed = threading.Event()
        self._conn: socket.socket | None = None
        self.thread = threading.Thread(target=self._serve, name=f"sim-{name}", daemon=True)

    @property
    def url(self) -> str:
        return f"socket://{self.host}:{self.port}"

    def start(self) -> "DeviceServer":
        self.thread.start()
        return self

    def close(self) -> None:
        self._closed.set()
        for s in (self._conn, self.sock):
            if s is not None:
                try:
                    s.shutdown(socket.SHUT_RDWR)
                except OSError:
                    pass
                s.close()
        if self.thread.ident is not None:     # join() raises for a thread never started
            self.thread.join(timeout=2)

    def _serve(self) -> None:
        while not self._closed.is_set():
            try:
                conn, _ = self.sock.accept()
            except OSError:
                return
            conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            self._conn = conn
            try:
                self._session(conn)
            except OSError:
                pass
            finally:
                try:
                    conn.close()
                except OSError:
                    pass
                self._conn = None

    def _session(self, conn: socket.socket) -> None:
        f = conn.makefile("rb")
        held = b""
        while not self._closed.is_set():
            line = f.readline()
            if not line:
                return
            reply, fault = self.handler(line)
            if reply is None or fault == "timeout":
                continue
            if fault == "late":
                held += reply
                continue
            if fault == "disconnect":
                conn.shutdown(socket.SHUT_RDWR)
                return
            if fault == "garble":
                reply = _corrupt(reply)
            elif fault == "partial":
                reply = reply[: max(1, len(reply) // 2)]
                if reply.endswith(b"\n"):
                    reply = reply[:-1]
            conn.sendall(held + reply)
            held = b""


class PtyServer:
    """Serve a handler on a pseudo-terminal; :attr:`url` is the slave device path (POSIX only)."""

    def __init__(self, handler, *, name: str = "device"):
        import tty

        self.handler, self.name = handler, name
        self.master, self.slave = os.openpty()
        tty.setraw(self.slave)
        self.url = os.ttyname(self.slave)
        self._closed = threading.Event()
        self.thread = threading.Thread(target=self._serve, name=f"pty-{name}", daemon=True)

    def start(self) -> "PtyServer":
        self.thread.start()
        return self

    def close(self) -> None:
        self._closed.set()
        for fd in (self.master, self.slave):
            try:
                os.close(fd)
            except OSError:
                pass

    def _serve(self) -> None:
        buf = b""
        held = b""
        while not self._closed.is_set():
            try:
                chunk = os.read(self.master, 4096)
            except OSError:
                return
            if not chunk:
                return
            buf += chunk
            while b"\n" in buf:
                line, buf = buf.split(b"\n", 1)
                reply, fault = self.handler(line + b"\n")
                if reply is None or fault in ("timeout", "disconnect"):
                    continue
                if fault == "late":
                    held += reply
                    continue
                if fault == "garble":
                    reply = _corrupt(reply)
                elif fault == "partial":
                    reply = reply[: max(1, len(reply) // 2)].rstrip(b"\n")
                view = memoryview(held + reply)
                held = b""
                while view:
                    n = os.write(self.master, view)
                    view = view[n:]
