"""Zaber ASCII protocol: message format and a stage driver over any pyserial-like port.

Command (host → device)::

    /<device> <axis> [<msg id>] <command> [<args>][:<CC>]\\n

Reply (device → host)::

    @<DD> <A> [<ID>] <OK|RJ> <IDLE|BUSY> <flag> <data>[\\][:<CC>]\\r\\n

``#`` lines are info messages, ``!`` lines alerts; a reply longer than a packet ends in
``\\`` and goes on in ``#<DD> <A> [<ID>] cont <more>`` packets. ``CC`` is the LRC:
the two's complement of the byte sum (mod 256) of everything between the leading
marker and the ``:``, as two hex digits. A device checks a command's ``CC`` whenever one
is sent but puts one on its own messages only with its setting ``comm.checksum`` = 1
(default 0). The message id (0–99) is echoed in the reply.

The flag field shows only the most urgent active flag (:data:`WARNING_FLAGS`): ``--``
none, ``F*`` faults, ``W*`` warnings (``WR`` no reference: ``home`` first; ``WL`` limit
sensor hit), ``N*`` notices (``NI`` move interrupted, ``NC`` manual knob); ``WT``
(controller hot) thus hides ``NI``. ``RJ`` replies carry the reason (``BADDATA``,
``BADCOMMAND``, ``BADAXIS``, ``AGAIN``, ``DEVICEONLY``, …) as data.

Positions are microsteps. ``home`` sets the position to ``limit.home.preset`` (0 on most
stages, not all). Microsteps → mm needs the product's microstep size, which the ASCII
protocol does not report (Zaber's libraries look it up by peripheral id in their device
database), so mehs keeps every stage quantity (``--pitch``, positions) in microsteps.

Reliability policy of :class:`ZaberStage`:

- Queries (``get pos``, ``warnings``, the empty poll) are idempotent and are
  retried up to ``retries`` times after a timeout, a partial or garbled reply.
- ``RJ AGAIN`` (device busy handling another packet) is retried after a delay.
- A motion command is **never repeated blindly**: after a lost reply or a
  disconnect the driver reconnects if needed, re-reads status, position and
  warnings, and re-issues the absolute move only if the stage is idle away
  from the target. Relative moves are not re-issued at all; ``home`` (which
  Zaber lists as safe to repeat) is re-issued whenever the stage is idle.
- Faults (``F*`` flags), ``NI``, ``WL``, ``NC``, ``WR`` after a move and rejections other
  than AGAIN raise :class:`~mehs.errors.DeviceError` at once.

References
----------
- Zaber Technologies, "ASCII Protocol Manual" (message format, reply flags,
  warning flags, checksums, ``home``), https://www.zaber.com/protocol-manual
- Zaber Motion Library, ``WarningFlags`` (flag names and priority order),
  https://github.com/zabertech/zaber-motion-lib-swift
- zproto (Rust), ``ascii/parse`` (continuation packets, LRC test vector
  ``"01 tools echo"`` → ``8F``), https://github.com/stphnt/zproto
"""

from __future__ import annotations

import re
import time
from dataclasses import dataclass, replace
from typing import Any, Callable

from mehs.capture.transport import Channel, SerialDriver
from mehs.errors import DeviceDisconnected, DeviceError, DeviceTimeout

#: Zaber's speed settings (``maxspeed``, ``move vel``) count in 1/1.6384 microsteps/s:
#: a setting of 1.6384 is one microstep per second (Zaber, "A-Series speed conversion";
#: the default maxspeed 153600 is 93750 microsteps/s).
SPEED_UNITS_PER_MICROSTEP_S = 1.6384


def speed_setting(microsteps_per_s: float) -> int:
    """The ``set maxspeed`` value for a speed in microsteps/s (at least 1)."""
    return max(1, int(round(float(microsteps_per_s) * SPEED_UNITS_PER_MICROSTEP_S)))


def speed_from_setting(value: float) -> float:
    """Microsteps/s of a ``maxspeed`` value."""
    return float(value) / SPEED_UNITS_PER_MICROSTEP_S

#: Warning flags, highest priority first (Zaber Motion Library ``WarningFlags``): the
#: reply's flag field shows the first active one.
WARNING_FLAGS = ("FF", "FN", "FZ", "FH", "FV", "FO", "FC", "FM", "FD", "FQ", "FI", "FA", "FR",
                 "FS", "FB", "FP", "FE", "FT",
                 "WL", "WV", "WT", "WS", "WM", "WP", "WR", "WH",
                 "NC", "NI", "ND", "NR", "NT", "NU", "NJ", "NB")

#: Besides the faults (``F*``), the flags after a finished move that mean the stage is not
#: where it was sent. The others (``WT`` hot, ``WV`` supply, ``WH``/``WP`` calibration,
#: ``NU``, …) are logged; the position check after an absolute move still applies.
MOTION_STOP_FLAGS = {"NI": "the move was interrupted",
                     "WL": "a limit sensor stopped the move (unexpected limit trigger)",
                     "NC": "the axis was moved with the manual knob",
                     "WR": "the axis has no reference position (home it)"}

_REPLY_RE = re.compile(
    r"^@(?P<dev>\d{2}) (?P<axis>\d+) (?:(?P<id>\d{1,2}) )?(?P<reply>OK|RJ) "
    r"(?P<status>IDLE|BUSY) (?P<flag>[-A-Z]{2}) (?P<data>.*?)(?::(?P<cc>[0-9A-F]{2}))?$")
_INFO_RE = re.compile(r"^#(?P<dev>\d{2}) (?P<axis>\d+) (?:(?P<id>\d{1,2}) )?(?P<data>.*?)"
                      r"(?::(?P<cc>[0-9A-F]{2}))?$")


def lrc(body: bytes) -> int:
    """Zaber checksum of ``body`` (the bytes between ``/``, ``@``, ``#`` or ``!`` and ``:``)."""
    return (-sum(body)) & 0xFF


def format_command(device: int, axis: int, command: str, *, checksum: bool = False,
                   msg_id: int | None = None) -> bytes:
    """Bytes of one command, e.g. ``format_command(1, 1, "move abs 1000") == b"/1 1 move abs 1000\\n"``."""
    parts = [str(int(device)), str(int(axis))]
    if msg_id is not None:
        parts.append(f"{int(msg_id) % 100:02d}")
    if command:
        parts.append(command)
    body = " ".join(parts).encode("ascii")
    if checksum:
        body += b":" + f"{lrc(body):02X}".encode("ascii")
    return b"/" + body + b"\n"


def format_reply(device: int, axis: int, ok: bool, busy: bool, flag: str, data: str, *,
                 checksum: bool = False, msg_id: int | None = None) -> bytes:
    """Bytes of one reply (used by the simulator and by tests)."""
    parts = [f"{int(device):02d}", str(int(axis))]
    if msg_id is not None:
        parts.append(f"{int(msg_id) % 100:02d}")
    parts += ["OK" if ok else "RJ", "BUSY" if busy else "IDLE", flag, data]
    body = " ".join(parts).encode("ascii")
    if checksum:
        body += b":" + f"{lrc(body):02X}".encode("ascii")
    return b"@" + body + b"\r\n"


class ZaberProtocolError(DeviceError):
    """A reply that does not follow the protocol (garbled, wrong device, bad checksum)."""


class StageRejected(DeviceError):
    """The stage answered ``RJ`` (the reason is in :attr:`reason`)."""

    def __init__(self, message: str, path=None, reason: str = ""):
        super().__init__(message, path)
        self.reason = reason


class StageFault(DeviceError):
    """The stage reports a fault flag (``F*``) or stopped away from its target."""


@dataclass(frozen=True)
class ZaberReply:
    """A parsed ``@`` reply."""

    device: int
    axis: int
    msg_id: int | None
    ok: bool
    busy: bool
    flag: str
    data: str

    @property
    def status(self) -> str:
        return "BUSY" if self.busy else "IDLE"


def _verify_checksum(text: str, cc: str | None) -> None:
    if cc is not None:
        body = text[1:text.rindex(":")].encode("ascii")
        if lrc(body) != int(cc, 16):
            raise ZaberProtocolError(f"checksum mismatch in {text!r}")


def _match(line: bytes | str, pattern: re.Pattern, what: str, verify_checksum: bool):
    """``pattern``'s match of one message line (terminator optional), its checksum checked."""
    text = line.decode("ascii", "replace") if isinstance(line, (bytes, bytearray)) else line
    text = text.rstrip("\r\n")
    m = pattern.match(text)
    if not m:
        raise ZaberProtocolError(f"garbled {what} {text!r}")
    if verify_checksum:
        _verify_checksum(text, m["cc"])
    return m


def parse_reply(line: bytes | str, *, verify_checksum: bool = True) -> ZaberReply:
    """Parse one ``@`` reply line (terminator optional).

    The message id may be one or two digits (Zaber's own parsers take any number);
    a reply continued in ``cont`` packets keeps its trailing ``\\`` in :attr:`data`.

    Raises
    ------
    ZaberProtocolError
        On anything that is not a well-formed reply (or a bad checksum).
    """
    m = _match(line, _REPLY_RE, "reply", verify_checksum)
    return ZaberReply(device=int(m["dev"]), axis=int(m["axis"]),
                      msg_id=None if m["id"] is None else int(m["id"]), ok=m["reply"] == "OK",
                      busy=m["status"] == "BUSY", flag=m["flag"], data=m["data"])


def parse_info(line: bytes | str, *, verify_checksum: bool = True) -> tuple[int, int, int | None, str]:
    """``(device, axis, msg id, data)`` of one ``#`` info line; raises ZaberProtocolError."""
    m = _match(line, _INFO_RE, "info message", verify_checksum)
    return int(m["dev"]), int(m["axis"]), None if m["id"] is None else int(m["id"]), m["data"]


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
        if self.checksum and not re.search(r":[0-9A-F]{2}$", text):
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
            m = re.fullmatch(r"cont(?: +(.*))?", data)
            if (m is None or (dev, axis) != (reply.device, reply.axis)
                    or mid not in (None, reply.msg_id)):
                self.info.append(text)
                continue
            self._require_checksum(text)
            more = (m[1] or "").strip()
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
        return _parse_warnings(self.query("warnings").data, self.name)

    def clear_warnings(self) -> list[str]:
        """Clear the clearable flags; returns the flags that were active."""
        return _parse_warnings(self.query("warnings clear").data, self.name)

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

    def _motion(self, command: str, target: int | None, wait: bool, *, home: bool = False) -> None:
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


def _parse_warnings(data: str, name: str) -> list[str]:
    parts = data.split()
    if not parts:
        raise ZaberProtocolError("empty warnings reply", name)
    try:
        n = int(parts[0])
    except ValueError:
        raise ZaberProtocolError(f"bad warnings reply {data!r}", name) from None
    flags = parts[1:]
    if n != len(flags):
        raise ZaberProtocolError(f"warnings reply counts {n} flags but lists {len(flags)}", name)
    return flags
