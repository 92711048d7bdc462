"""A GVSP relay that loses or delays packets on purpose: incomplete and late buffers for the fault tests.

GigE Vision streams frames as UDP packets (GVSP): a leader, data packets, a
trailer, all tagged with the frame's block id. Aravis's fake camera sends them
to the stream destination the receiver wrote into the camera's bootstrap
registers (SCDA / SCP0). The relay watches those registers, puts itself in
between (rewriting the port once the receiver has set it), and forwards every
packet, except

* the data packets of the frames ``drop(n)`` selects (n = 1-based frame
  count): the receiver then gets a leader and a trailer without data, as when
  packets are lost on a real link, and reports an incomplete buffer;
* all packets of the frames ``hold(n)`` selects, which are kept and sent just
  before the camera's next frame (a frame delayed past the receiver's timeout
  — a congested switch, a camera slow to read out — that then arrives whole and
  in order: Aravis discards a frame older than one it has already seen, so
  a late frame is delivered only when it comes before the next one);

and, with ``delay_s``, forwards every packet that much later (a link with a
constant latency: frames keep arriving for ``delay_s`` after the camera stopped
sending, as a frame in flight across AcquisitionStop does).

References
----------
AIA, *GigE Vision 2.0*, 2011, §22 "GVSP header" and §28 bootstrap registers
(SCP0 0x0D00: host port in bits 0–15; SCDA0 0x0D18).
"""

from __future__ import annotations

import collections
import socket
import struct
import threading
import time
from typing import Callable

SCP0, SCDA0 = 0x0D00, 0x0D18
_LEADER, _TRAILER, _DATA = 1, 2, 3


def gvsp_header(packet: bytes) -> tuple[int, int]:
    """``(packet format, block id)`` of a GVSP packet (standard or extended-id header)."""
    fmt_byte = packet[4]
    if fmt_byte & 0x80:                       # EI flag: 64-bit block id at bytes 8..15
        return fmt_byte & 0x0F, struct.unpack(">Q", packet[8:16])[0]
    return fmt_byte & 0x0F, struct.unpack(">H", packet[2:4])[0]


class StreamRelay:
    """Forward GVSP from the fake camera to the receiver, dropping the data of selected frames."""

    def __init__(self, fake_camera, *, drop: Callable[[int], bool] = lambda n: False,
                 hold: Callable[[int], bool] = lambda n: False, delay_s: float = 0.0):
        self.fc, self.drop, self.hold = fake_camera, drop, hold
        self.delay_s = max(0.0, float(delay_s))
        self._delayed: collections.deque[tuple[float, bytes]] = collections.deque()  # (due, packet)
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4 << 20)
        self.sock.bind(("127.0.0.1", 0))
        self.sock.settimeout(0.05)
        self.port = self.sock.getsockname()[1]
        self.dest: tuple[str, int] | None = None
        self.frames = 0
        self.dropped_frames: list[int] = []
        self.held_frames: list[int] = []
        self._dropping: int | None = None
        self._holding: int | None = None          # block id of the frame being held
        self._held: list[bytes] = []
        self._closed = threading.Event()
        self._threads = [threading.Thread(target=self._watch, daemon=True, name="gvsp-relay-watch"),
                         threading.Thread(target=self._forward, daemon=True, name="gvsp-relay")]

    def start(self) -> "StreamRelay":
        for t in self._threads:
            t.start()
        return self

    def close(self) -> None:
        self._closed.set()
        for t in self._threads:
            t.join(timeout=1)
        self.sock.close()

    def _reg(self, addr: int) -> int:
        return int(self.fc.read_register(addr)[1])

    def _watch(self) -> None:
        # The receiver writes its port when it creates its stream, long before
        # AcquisitionStart; re-point the camera at the relay whenever it does.
        while not self._closed.wait(0.0005):
            try:
                scp = self._reg(SCP0)
                port = scp & 0xFFFF
                if port and port != self.port:
                    ip = socket.inet_ntoa(struct.pack(">I", self._reg(SCDA0)))
                    self.dest = (ip, port)
                    self.fc.write_register(SCP0, (scp & 0xFFFF0000) | self.port)
            except Exception:   # the camera was unplugged
                return

    def _forward(self) -> None:
        while not self._closed.is_set():
            self._send_due()
            # wake in time for the next delayed packet (one delay for all: first in, first due)
            wait = min(0.05, max(1e-4, self._delayed[0][0] - time.monotonic())) if self._delayed else 0.05
            try:
                self.sock.settimeout(wait)
                pkt, _ = self.sock.recvfrom(65536)
            except socket.timeout:
                continue
            except OSError:
                return
            if self.dest is None or len(pkt) < 8:
                continue
            fmt, block = gvsp_header(pkt)
            if fmt == _LEADER:
                self.frames += 1
                held, self._held = self._held, []
                for old in held:              # the late frame arrives just before this one
                    self._send(old)
                self._dropping = block if self.drop(self.frames) else None
                if self._dropping is not None:
                    self.dropped_frames.append(self.frames)
                self._holding = block if self.hold(self.frames) else None
                if self._holding is not None:
                    self.held_frames.append(self.frames)
            elif fmt == _DATA and block == self._dropping:
                continue
            if self._holding is not None and block == self._holding:
                self._held.append(pkt)
                continue
            self._send(pkt)

    def _send(self, pkt: bytes) -> None:
        if self.delay_s > 0:
            self._delayed.append((time.monotonic() + self.delay_s, pkt))
        else:
            self._send_now(pkt)

    def _send_due(self) -> None:
        now = time.monotonic()
        while self._delayed and self._delayed[0][0] <= now:
            self._send_now(self._delayed.popleft()[1])

    def _send_now(self, pkt: bytes) -> None:
        try:
            self.sock.sendto(pkt, self.dest)
        except OSError:
            time.sleep(0.001)
