"""Zaber stage driver: one axis over any pyserial-like port, speaking the ASCII protocol.

The message grammar (formatting, checksums, reply/info parsing, flag tables) lives in
:mod:`mehs.capture.zaber_protocol`; its public names are re-exported here, where the rest
of mehs imports them from. Positions are microsteps. ``home`` sets the position to
``limit.home.preset`` (0 on most stages, not all). Microsteps → mm needs the product's
microstep size, which the ASCII protocol does not report (Zaber's libraries look it up by
peripheral id in their device database), so mehs keeps every stage quantity (``--pitch``,
positions) in microsteps.

Reliability policy of :class:`ZaberStage`:

- Queries (``get pos``, ``warnings``, the empty poll) are idempotent and are
  retried up to ``retries`` times after a timeout, a partial or garbled reply.
- ``RJ AGAIN`` (device busy handling another packet) is retried after a delay.
- A motion command is **never repeated blindly**: after a lost reply or a
  disconnect the driver reconnects if needed, re-reads status, position and
  warnings, and re-issues the absolute move only if the stage is idle away
  from the target. Relative moves are not re-issued at all; ``home`` (which
  Zaber lists as safe to repeat) is re-issued whenever the stage is idle.
- Before a motion command, latched flags left from before it
  (:data:`~mehs.capture.zaber_protocol.STALE_NOTICE_FLAGS`: ``NI`` from an earlier stop,
  ``NC`` from the knob, ``WL``, the other ``N*`` notices) are cleared with ``warnings
  clear`` and named in :attr:`ZaberStage.events`, so that a flag after the move is this
  move's own. This costs a ``warnings`` round trip only when the last reply's flag field
  showed a flag (or no reply was read yet); a step scan, whose polls show ``--``, pays
  nothing. A fault (``F*``) set before a motion is never cleared: the motion is refused
  with a :class:`StageFault` saying what to do. ``WR`` is left to ``home``.
- Faults (``F*`` flags), ``NI``, ``WL``, ``NC``, ``WR`` after a move and rejections other
  than AGAIN raise :class:`~mehs.errors.DeviceError` at once.

References
----------
- Zaber Technologies, "ASCII Protocol Manual" (message format, reply flags,
  warning flags and ``warnings clear``, ``home``), https://www.zaber.com/protocol-manual
- Zaber Motion Library, ``WarningFlags`` (flag names and priority order),
  https://github.com/zabertech/zaber-motion-lib-swift
"""

from __future__ import annotations

import time
from dataclasses import replace
from typing import Any, Callable

from mehs.capture.transport import Channel, SerialDriver
from mehs.capture.zaber_protocol import (  # noqa: F401  (re-exported: mehs imports them here)
    MOTION_STOP_FLAGS, SPEED_UNITS_PER_MICROSTEP_S, STALE_NOTICE_FLAGS, WARNING_FLAGS,
    ZaberProtocolError, ZaberReply, continuation_text, format_command, format_reply,
    format_warnings, has_checksum, lrc, parse_info, parse_reply, parse_warnings,
    speed_from_setting, speed_setting)
from mehs.errors import DeviceDisconnected, DeviceError, DeviceTimeout

__all__ = ["MOTION_STOP_FLAGS", "SPEED_UNITS_PER_MICROSTEP_S", "STALE_NOTICE_FLAGS",
           "WARNING_FLAGS", "StageFault", "StageRejected", "ZaberProtocolError", "ZaberReply",
           "ZaberStage", "continuation_text", "format_command", "format_reply",
           "format_warnings", "has_checksum", "lrc", "parse_info", "parse_reply",
           "parse_warnings", "speed_from_setting", "speed_setting"]


class StageRejected(DeviceError):
    """The stage answered ``RJ`` (the reason is in :attr:`reason`)."""

    def __init__(self, message: str, path=None, reason: str = ""):
        super().__init__(message, path)
        self.reason = reason


class StageFault(DeviceError):
    """The stage reports a fault flag (``F*``) or stopped away from its target."""


class ZaberStage(SerialDriver):
    """Driver for one axis of a Zaber stage speaking the ASCII protocol.

    Parameters
    ----------
    port
        An open pyserial-like port (see :func:`mehs.capture.transport.open_port`).
    device, axis
        Device address (1 = first in the chain) and axis number (1-based).
    checksum
        Append ``:CC`` to commands and require it to be valid on replies. A device
        verifies a command's checksum whenever one is sent, but adds one to its
        replies only with its ``comm.checksum`` setting at 1 (default 0).
    message_ids
        Number each command (ids 0–99, the ASCII protocol's message id) and take
        only the reply that echoes it. A reply that comes after its timeout (a slow
        link, a busy device) is then dropped as stale instead of being read as the
        answer to the next command — without ids every later reply is one behind,
        and ``get pos`` may read a poll's ``0``. ``False`` for a device that does
        not echo ids.
    opener
        Callable re-opening the port after a disconnect.
    retries
        Re-tries of an idempotent query after a timeout/garbled reply, and
        informed re-issues of an absolute move.
    reconnects
        Reconnection attempts after a disconnect before giving up.
    poll_interval_s, move_timeout_s
        Polling period while BUSY, and the longest a move may take.
    """

    def __init__(self, port: Any, *, device: int = 1, axis: int = 1, checksum: bool = False,
                 message_ids: bool = True, opener: Callable[[], Any] | None = None,
                 name: str | None = None,
                 retries: int = 3, reconnects: int = 3, again_retries: int = 10,
                 poll_interval_s: float = 0.002, move_timeout_s: float = 120.0,
                 retry_delay_s: float = 0.02):
        self.channel = Channel(port, opener=opener, name=name)
        self.device, self.axis, self.checksum = int(device), int(axis), bool(checksum)
        self.message_ids = bool(message_ids)
        self._next_id = 0
        self.retries, self.reconnects, self.again_retries = int(retries), int(reconnects), int(again_retries)
        self.poll_interval_s, self.move_timeout_s = float(poll_interval_s), float(move_timeout_s)
        self.retry_delay_s = float(retry_delay_s)
        self.last_reply: ZaberReply | None = None
        self.info: list[str] = []
        self.alerts: list[str] = []
        self.events: list[str] = []   # recoveries, for the capture log
        self.home_position: int | None = None
        self._logged_flags: list[str] = []
        # the last `warnings` reply and its flags: a motion right after it needs no re-read
        self._warnings_read: tuple[ZaberReply, list[str]] | None = None

    # ------------------------------------------------------------ low level
    def _read_reply(self, expect_id: int | None = None) -> ZaberReply:
        """The reply to the command just sent: with ``expect_id``, replies carrying
        another id (late answers to earlier commands) are dropped and logged."""
        for _ in range(64):  # info/alert lines and stale replies may precede the reply
            raw = self.channel.read_line(b"\n", what="stage reply")
            text = raw.decode("ascii", "replace").rstrip("\r\n")
            if text.startswith("#"):
                self.info.append(text)
                continue
            if text.startswith("!"):
                self.alerts.append(text)
                continue
            try:
                reply = parse_reply(text, verify_checksum=True)
            except ZaberProtocolError as exc:
                raise ZaberProtocolError(exc.problem, self.name) from None
            self._require_checksum(text)
            if reply.device != self.device or reply.axis not in (self.axis, 0):
                raise ZaberProtocolError(
                    f"reply from device {reply.device} axis {reply.axis}, expected "
                    f"{self.device} {self.axis}: {text!r}", self.name)
            if expect_id is not None:
                if reply.msg_id is None:
                    raise ZaberProtocolError(
                        f"reply without the message id {expect_id:02d} the command carried: "
                        f"{text!r} (a device that does not echo ids: message_ids=False, "
                        "or mehs capture --no-message-ids)", self.name)
                if reply.msg_id != expect_id:
                    self.events.append(f"stage: dropped a late reply {text!r} "
                                       f"(id {reply.msg_id:02d}, waiting for {expect_id:02d})")
                    continue
            if reply.data.endswith("\\"):
                reply = self._read_continuation(reply)
            return reply
        raise ZaberProtocolError("too many info/alert lines or stale replies without the reply",
                                 self.name)

    def _require_checksum(self, text: str) -> None:
        if self.checksum and not has_checksum(text):
            # a Zaber device checks a command's checksum when one is sent, but adds one
            # to its replies only with its comm.checksum setting at 1 (default 0)
            raise ZaberProtocolError(
                f"reply without checksum {text!r}: the device adds checksums to its replies "
                "only with comm.checksum = 1 (send '/set comm.checksum 1' once), or run "
                "without --checksum", self.name)

    def _read_continuation(self, reply: ZaberReply) -> ZaberReply:
        """Join a reply ending in ``\\`` with its ``#.. cont`` packets (a reply longer than
        the device's packet size, ``comm.packet.size.max``, 80 bytes by default)."""
        parts = [reply.data[:-1].rstrip()]
        for _ in range(64):
            text = self.channel.read_line(b"\n", what="continuation of a stage reply")
            text = text.decode("ascii", "replace").rstrip("\r\n")
            if text.startswith("!"):
                self.alerts.append(text)
                continue
            if not text.startswith("#"):
                raise ZaberProtocolError(f"expected the 'cont' packets of the reply "
                                         f"{parts[0]!r}, got {text!r}", self.name)
            try:
                dev, axis, mid, data = parse_info(text)
            except ZaberProtocolError as exc:
                raise ZaberProtocolError(exc.problem, self.name) from None
            more = continuation_text(data)
            if (more is None or (dev, axis) != (reply.device, reply.axis)
                    or mid not in (None, reply.msg_id)):
                self.info.append(text)
                continue
            self._require_checksum(text)
            if more.endswith("\\"):
                parts.append(more[:-1].rstrip())
                continue
            parts.append(more)
            return replace(reply, data=" ".join(x for x in parts if x))
        raise ZaberProtocolError("a continued reply never ended", self.name)

    def _take_id(self) -> int | None:
        if not self.message_ids:
            return None
        i = self._next_id
        self._next_id = (i + 1) % 100
        return i

    def _send_once(self, command: str) -> ZaberReply:
        """One command, one reply; RJ AGAIN is re-sent (the device did not act on it)."""
        for attempt in range(self.again_retries + 1):
            # a new id per attempt: a late answer to an earlier attempt is not this one's
            mid = self._take_id()
            self.channel.write(format_command(self.device, self.axis, command,
                                              checksum=self.checksum, msg_id=mid))
            reply = self._read_reply(mid)
            self.last_reply = reply
            if reply.ok:
                return reply
            reason = reply.data.strip()
            if reason == "AGAIN" and attempt < self.again_retries:
                time.sleep(self.retry_delay_s)
                continue
            raise StageRejected(f"stage rejected {command!r}: {reason} (flag {reply.flag})",
                                self.name, reason=reason)
        raise AssertionError("unreachable")

    def query(self, command: str) -> ZaberReply:
        """Send an idempotent command; retried after timeouts, garbled replies and disconnects."""
        last: DeviceError | None = None
        for attempt in range(self.retries + 1):
            try:
                return self._send_once(command)
            except (DeviceTimeout, ZaberProtocolError, DeviceDisconnected) as exc:
                last = exc
                self.events.append(f"stage: {type(exc).__name__} on {command!r}: {exc.problem}")
                if attempt < self.retries:
                    self._recover(exc)
        raise type(last)(f"{last.problem} (after {self.retries + 1} attempts of {command!r})",
                         self.name)

    # ------------------------------------------------------------ queries
    def poll(self) -> ZaberReply:
        """The empty command: status (IDLE/BUSY) and flag."""
        return self.query("")

    def position(self) -> int:
        """Current position (microsteps)."""
        r = self.query("get pos")
        try:
            return int(r.data.split()[0])
        except (ValueError, IndexError):
            raise ZaberProtocolError(f"position reply {r.data!r} is not an integer", self.name) from None

    def warnings(self) -> list[str]:
        """Active warning/fault/notice flags (``warnings`` command)."""
        r = self.query("warnings")
        flags = parse_warnings(r.data, self.name)
        self._warnings_read = (r, flags)
        return flags

    def clear_warnings(self) -> list[str]:
        """Clear the clearable flags (faults included); returns the flags that were active."""
        return parse_warnings(self.query("warnings clear").data, self.name)

    def is_homed(self) -> bool:
        return "WR" not in self.warnings()

    def state(self) -> dict[str, Any]:
        """Status, position and warnings, re-read from the device."""
        r = self.poll()
        return {"status": r.status, "position": self.position(), "warnings": self.warnings()}

    def reconnect(self) -> dict[str, Any]:
        """Re-open the port, then re-read status, position and warnings (no motion)."""
        last: DeviceError | None = None
        for attempt in range(self.reconnects):
            try:
                self.channel.reopen()
                st = self.state()
                self.events.append(f"stage: reconnected, {st}")
                return st
            except DeviceError as exc:
                last = exc
                time.sleep(min(0.05 * 2 ** attempt, 1.0))
        raise DeviceDisconnected(f"could not reconnect after {self.reconnects} attempts "
                                 f"({last.problem if last else 'no attempt'})", self.name)

    # ------------------------------------------------------------ motion
    def _check_flags(self, flags: list[str], what: str) -> None:
        """Raise StageFault on a fault or a :data:`MOTION_STOP_FLAGS` flag; log the rest once."""
        faults = [f for f in flags if f.startswith("F")]
        if faults:
            raise StageFault(f"stage fault {' '.join(faults)} {what}; warnings {flags}", self.name)
        for f in flags:
            if f in MOTION_STOP_FLAGS:
                raise StageFault(f"{MOTION_STOP_FLAGS[f]} ({f}) {what}; warnings {flags}",
                                 self.name)
        info = sorted(set(flags))
        if info and info != self._logged_flags:
            self.events.append(f"stage: warning flags {' '.join(info)} {what}")
        self._logged_flags = info

    def wait_idle(self, *, target: int | None = None, _flags_read_by_caller: bool = False) -> ZaberReply:
        """Poll until IDLE; raise on a fault, a :data:`MOTION_STOP_FLAGS` flag or a timeout.

        The flag field shows only the highest-priority flag (``WT`` hides ``NI``), so
        a move that ends showing any flag has its full warning list read."""
        deadline = time.monotonic() + self.move_timeout_s
        while True:
            r = self.poll()
            if r.flag.startswith("F"):
                raise StageFault(f"stage fault {r.flag}; warnings {self.warnings()}", self.name)
            if not r.busy:
                break
            if time.monotonic() > deadline:
                raise DeviceTimeout(f"stage still BUSY after {self.move_timeout_s} s", self.name)
            time.sleep(self.poll_interval_s)
        if r.flag in MOTION_STOP_FLAGS and r.flag != "WR":
            raise StageFault(f"{MOTION_STOP_FLAGS[r.flag]} ({r.flag}); warnings {self.warnings()}",
                             self.name)
        if r.flag != "--" and not _flags_read_by_caller:
            self._check_flags(self.warnings(), "after the move")
        if target is not None:
            pos = self.position()
            if pos != target:
                raise StageFault(f"stage stopped at {pos} instead of {target} (flag {r.flag})", self.name)
        return r

    def _clear_stale_notices(self, command: str) -> None:
        """Before ``command`` (a motion): clear the latched flags left from before it, naming
        them in :attr:`events`; refuse on a fault, which is never cleared here.

        The flag field shows a flag whenever any is set, so a last reply showing ``--``
        needs no ``warnings`` read (the step scan's case); the full list is read otherwise,
        as ``WR`` or ``WT`` outrank the notices there.
        """
        r = self.last_reply
        if r is not None and r.flag == "--":
            return
        if self._warnings_read is not None and self._warnings_read[0] is r:
            flags = self._warnings_read[1]          # just read (e.g. at the session start)
        else:
            flags = self.warnings()
        where = f"'/{self.device} {self.axis} warnings clear'"
        faults = [f for f in flags if f.startswith("F")]
        if faults:
            raise StageFault(f"stage fault {' '.join(faults)} is set: {command!r} was not sent. "
                             "Check the mechanics (stall, obstruction, supply, cable), then clear "
                             f"it with {where} or Zaber Launcher (mehs never clears a fault "
                             f"itself); warnings {flags}", self.name)
        if not any(f in STALE_NOTICE_FLAGS for f in flags):
            return
        before = self.clear_warnings()
        cleared = [f for f in before if f in STALE_NOTICE_FLAGS or f.startswith("F")]
        faults = [f for f in before if f.startswith("F")]
        if faults:  # raised between the two reads and cleared with the notices: say so
            raise StageFault(f"stage fault {' '.join(faults)} appeared just before {command!r} "
                             f"and was cleared with the stale notices by {where}; the move "
                             f"was not sent: check the mechanics before going on", self.name)
        self.events.append(f"stage: cleared stale flags {' '.join(cleared)} before {command!r} "
                           "(set before this move: an earlier stop, the manual knob or another "
                           "program; Zaber 'warnings clear')")

    def _motion(self, command: str, target: int | None, wait: bool, *, home: bool = False) -> None:
        self._clear_stale_notices(command)
        issues = 0
        while True:
            try:
                r = self._send_once(command)
                break
            except (DeviceTimeout, ZaberProtocolError, DeviceDisconnected) as exc:
                self.events.append(f"stage: {type(exc).__name__} on {command!r}: {exc.problem}")
                self._recover(exc)
                # Never repeat a motion blindly: look at what the stage did.
                st = self.state()
                if any(w.startswith("F") for w in st["warnings"]):
                    raise StageFault(f"stage fault {st['warnings']} after {command!r}", self.name) from None
                if st["status"] == "BUSY":
                    r = self.last_reply
                    break  # it received the command and is moving; wait for it below
                # A lost home is sent again: Zaber lists home as safe to repeat, and where it
                # ends (limit.home.preset) is not known here, so an idle stage at some
                # position without WR may or may not have homed just now.
                if target is not None and st["position"] == target and not home:
                    return self._finish(target, wait, home)
                if (target is None and not home) or issues >= self.retries:
                    raise DeviceError(f"{command!r} may not have been executed and cannot be "
                                      f"safely repeated; stage state {st}", self.name) from None
                issues += 1
                self.events.append(f"stage: re-issuing {command!r} from position {st['position']}")
        if r is not None and r.flag.startswith("F"):
            raise StageFault(f"stage fault {r.flag} on {command!r}", self.name)
        self._finish(target, wait, home)

    def _finish(self, target: int | None, wait: bool, home: bool) -> None:
        if wait:
            self.wait_idle(target=target, _flags_read_by_caller=home)

    def home(self, *, wait: bool = True) -> None:
        """Home the axis; with ``wait``, a ``WR`` (no reference) left after it is a fault.

        Homing sets the position to the axis setting ``limit.home.preset`` (0 on most
        stages); the position it ended at is kept in :attr:`home_position`.
        """
        self._motion("home", None, wait, home=True)
        if wait:
            self.home_position = self.position()
            flags = self.warnings()
            if "WR" in flags:
                raise StageFault("homing ended without a reference position (WR still set)",
                                 self.name)
            self._check_flags(flags, "after homing")

    def move_abs(self, position: int, *, wait: bool = True) -> None:
        """Move to ``position`` (microsteps); waits until IDLE there when ``wait``."""
        position = int(position)
        self._motion(f"move abs {position}", position, wait)

    def move_rel(self, delta: int, *, wait: bool = True) -> None:
        """Move by ``delta`` microsteps (never re-issued after a lost reply)."""
        self._motion(f"move rel {int(delta)}", None, wait)

    def stop(self) -> None:
        self._send_once("stop")
