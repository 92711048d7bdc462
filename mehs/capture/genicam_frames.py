"""Frames of a GenICam camera: which frame belongs to a triggered line, and free-running streams.

Step mode (:class:`TriggerLedger`)
    A line is software-triggered at a stage position; when its frame does not
    come within the timeout the line is triggered again (same position). The
    first trigger's frame may still come: late (a congested link, a camera slow
    to read out), possibly after the stage moved on and the next line was
    triggered — read as that line's data, it would be a silent wrong line.
    Two facts tell a late frame from the current one:

    * causality (host clock): Aravis stamps a buffer with the host time its
      GVSP/U3V leader arrived (``arv_buffer_get_system_timestamp``); a frame
      whose leader came before the line's first trigger was sent is not this
      line's;
    * block ids: a GigE Vision / USB3 Vision camera numbers the blocks it sends
      (``arv_buffer_get_frame_id``): 16 bits in GVSP 1.x, wrapping from 65535
      to 1 (0 is invalid; some cameras send it anyway), 64 bits with GEV 2.x
      extended ids and in U3V. A camera sends one frame per software trigger,
      so the frame of the k-th trigger is numbered k after the first one seen;
      a frame numbered before the line's first trigger is an earlier trigger's.
      (Aravis itself already discards a frame older than one it has delivered,
      so a late frame only ever arrives ahead of newer ones.)

    A camera may ignore a trigger that comes while it is busy — then a trigger
    yields no frame and the count runs ahead, and the current line's frame looks
    like an earlier one's. That shows as a dropped "stale" frame followed by a
    full timeout of silence; the ledger then re-synchronises on the last frame
    seen (the retry's frame counts from there), losing one timeout, not a line.

Continuous mode (:class:`FrameStream`)
    Free-running acquisition; frames are taken as they come, with host times.

References
----------
AIA, *GigE Vision 2.0*, 2011, §22 (GVSP block_id: 16 bits, 0 reserved; 64-bit
extended ids). AIA, *USB3 Vision 1.0*, 2013, §5.5 (leader block id, 64 bits).
E. Pacaud, *Aravis 0.8 API reference*, ArvBuffer (``get_frame_id``,
``get_system_timestamp``) and arvgvstream.c ("Discard late frame").
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from mehs.errors import DeviceError

if TYPE_CHECKING:
    from mehs.capture.genicam import GenicamCamera

#: Largest GVSP 1.x block id; a larger id is a 64-bit (extended / U3V) one, which never wraps.
GVSP_ID_MAX = 0xFFFF


def id_step(last: int, raw: int) -> int:
    """Frames from block id ``last`` to ``raw`` (negative: ``raw`` is older).

    16-bit GVSP ids wrap from 65535 to 1 (0 reserved), or to 0 on cameras that
    send it (as Aravis's fake camera): both count as one step, as Aravis counts.
    """
    if last > GVSP_ID_MAX or raw > GVSP_ID_MAX:
        return raw - last
    d = (raw - last) % (GVSP_ID_MAX + 1)
    if d > (GVSP_ID_MAX + 1) // 2:             # older
        d -= GVSP_ID_MAX + 1
        return d + 1 if raw > last and last != 0 else d   # back across the reserved id 0
    if raw < last and raw != 0:
        d -= 1                                  # wrapped past the reserved id 0
    return d


class TriggerLedger:
    """Step-mode bookkeeping: the frames of a line's triggers, and those of earlier lines.

    Sequence numbers are block ids unwrapped to a monotonic count. ``frame_ids``
    False trusts no ids (a camera that does not number its frames): only the
    causality check is made.
    """

    def __init__(self, name: str, *, frame_ids: bool = True):
        self.name, self.frame_ids = name, bool(frame_ids)
        self.reset()

    def reset(self) -> None:
        """A new acquisition (AcquisitionStart may restart the camera's numbering)."""
        self.raw: int | None = None          # block id of the last frame seen
        self.seq: int | None = None          # its sequence number
        self.next: int | None = None         # sequence number the next trigger's frame will have
        self.line_start: int | None = None   # lowest sequence number of the current line's frames
        self.line_t0_ns = 0                  # host time just before the line's first trigger
        self.stale_in_line = False

    def begin_line(self, t0_ns: int) -> None:
        self.line_start, self.line_t0_ns, self.stale_in_line = self.next, int(t0_ns), False

    def triggered(self) -> None:
        if self.next is not None:
            self.next += 1

    def seen(self, raw: int) -> int | None:
        """Record a frame's block id; its sequence number (None without id checks)."""
        if not self.frame_ids:
            return None
        raw = int(raw)
        if self.raw is None:
            seq = raw
        else:
            step = id_step(self.raw, raw)
            if step <= 0:
                raise DeviceError(
                    f"camera frame ids do not increase (frame {raw} came after frame {self.raw}), so a "
                    "late frame of an abandoned trigger cannot be told from this line's. For a camera "
                    "that does not number its frames, turn the check off: camera URL "
                    "aravis://DEVICE?frame-ids=off (GenicamCamera(..., frame_ids=False)); late frames "
                    "are then caught only when they arrive before the line's trigger", self.name)
            seq = self.seq + step
        self.raw, self.seq = raw, seq
        if self.next is None or seq >= self.next:
            self.next = seq + 1                  # frames lost on the way: count on from this one
        return seq

    def stale_reason(self, raw: int, system_ns: int) -> str | None:
        """Record a received frame; why it is not the current line's, or None when it is."""
        seq = self.seen(raw)
        why = None
        # g_get_real_time() has µs resolution: compare in whole µs
        if 0 < system_ns // 1000 < self.line_t0_ns // 1000:
            why = f"arrived {(self.line_t0_ns - system_ns) / 1e6:.1f} ms before the line's trigger"
        elif seq is not None and self.line_start is not None and seq < self.line_start:
            why = f"{self.line_start - seq} frame(s) before the line's first trigger"
        if why is not None:
            self.stale_in_line = True
        return why

    def timed_out(self) -> bool:
        """A trigger got no frame in time; re-synchronise when a dropped "stale" frame may have been
        this line's (the camera ignored an earlier trigger). True when it did."""
        if not (self.stale_in_line and self.frame_ids and self.seq is not None):
            return False
        self.line_start = self.next = self.seq + 1
        self.stale_in_line = False
        return True


@dataclass
class Frame:
    """One received spectral frame.

    ``line``: uint16 ``(samples, bands)``; ``t``: host time (s) of mid-exposure.
    """

    line: np.ndarray
    t: float
    frame_id: int


#: Shortest quiet time (s) that ends the flush after a free-running acquisition stops
#: (:meth:`FrameStream.flush_quiet_s`): a loaded host's scheduling stalls, not the link's jitter.
FLUSH_QUIET_MIN_S = 0.3


class FrameStream:
    """Free-running acquisition; :meth:`poll` returns the frames received so far with host times.

    Host time of a frame = camera timestamp + clock offset + t_exposure / 2
    (timestamps mark the exposure start: GigE Vision cameras latch them at the
    frame-start trigger). A camera whose clock is the host's (IEEE 1588 PTP
    synchronised; the simulator) needs no offset; otherwise the offset is the
    smallest ``system_timestamp − timestamp`` seen (the minimum transfer
    latency, as NTP's minimum-delay filter), which places frames late by at
    most the fastest frame's transfer time.
    """

    def __init__(self, camera: "GenicamCamera", frame_rate_hz: float):
        self.cam = camera
        self.requested = float(frame_rate_hz)
        self.rate = None
        self._raw: list[tuple[np.ndarray, int, int, int]] = []
        self._offset_ns: int | None = None

    def __enter__(self) -> "FrameStream":
        c = self.cam
        c._stop()
        self.rate = c.set_frame_rate(self.requested)
        c._start("free")
        return self

    def __exit__(self, *exc: Any) -> None:
        self.cam._stop(flush_s=self.flush_quiet_s())

    def flush_quiet_s(self) -> float:
        """Quiet time that shows the frames sent before AcquisitionStop have all arrived.

        While a free-running camera's frames are still on the way they arrive about one frame
        period apart, give or take the link's jitter (the spread of ``system − camera``
        timestamps seen, clock offset cancelling), plus the frame the camera finishes
        exposing; a gap of two periods, one exposure and twice the jitter means the pipe is
        empty. A busy host also stalls the delivery of frames already on the way, by more
        than any jitter the stream showed (CI, two cores under load: a 150 ms link's lit
        frame slipped past a 62 ms wait into a dark reference), so the wait is at least
        :data:`FLUSH_QUIET_MIN_S`, paid once per switch out of free-running. The camera caps
        it at its frame timeout.
        """
        period = 1.0 / self.rate if self.rate else 0.0
        jitter = 0.0
        if self._raw:
            lat = np.array([s - t for _l, t, s, _f in self._raw], dtype=np.float64)
            # a robust spread: frames a camera sent from its buffer after a stall arrive
            # late by up to the stall, which says nothing about the link's jitter
            lo, hi = np.percentile(lat, [5.0, 95.0])
            jitter = float(hi - lo) / 1e9
        return max(2 * period + (self.cam._t_ms or 0.0) / 1000.0 + 2 * jitter, FLUSH_QUIET_MIN_S)

    def poll(self, timeout_s: float = 0.0) -> list[Frame]:
        """Frames received since the last call (waiting up to ``timeout_s`` for the first)."""
        c = self.cam
        out: list[Frame] = []
        wait = int(max(timeout_s, 0.0) * 1e6)
        while True:
            b = c._pop(wait)
            if b is None:
                break
            wait = 0
            if b is False:
                continue
            try:
                line = c._decode(b)
                ts, sys_ts, fid = int(b.get_timestamp()), int(b.get_system_timestamp()), int(b.get_frame_id())
            finally:
                c._stream.push_buffer(b)
            off = sys_ts - ts
            self._offset_ns = off if self._offset_ns is None else min(self._offset_ns, off)
            self._raw.append((line, ts, sys_ts, fid))
            out.append(Frame(line, 0.0, fid))
        return out

    def _clock_offset_ns(self) -> int:
        if self._raw and abs(float(np.median([s - t for _l, t, s, _f in self._raw]))) < 1e9:
            # the camera clock already is the host's (IEEE 1588 PTP, or the simulator): no offset
            return 0
        return self._offset_ns or 0

    def newest_start(self) -> float | None:
        """Host time (s) at which the newest frame received so far began its exposure."""
        if not self._raw:
            return None
        return (self._raw[-1][1] + self._clock_offset_ns()) / 1e9

    def frames(self) -> list[Frame]:
        """All frames with host mid-exposure times (final clock offset applied)."""
        half = (self.cam._t_ms or 0.0) / 2000.0
        off = self._clock_offset_ns()
        return [Frame(line, (ts + off) / 1e9 + half, fid) for line, ts, _s, fid in self._raw]
