"""Zaber ASCII protocol: the message grammar, the checksum and the flag tables.

No I/O here: :mod:`mehs.capture.zaber` (the driver) and :mod:`mehs.capture.simdevice`
(the simulated stage) both build and read messages with these functions, so the two
sides cannot drift apart. Imports flow one way: this module ← the driver ← the simulator.

Command (host → device)::

    /[<device> [<axis> [<msg id>]]] [<command> [<args>]][:<CC>]\\n

Reply (device → host)::

    @<DD> <A> [<ID>] <OK|RJ> <IDLE|BUSY> <flag> <data>[\\][:<CC>]\\r\\n

``DD`` is the device address as two digits (``01``; 0–99), ``A`` the axis (``0`` = the
whole device), ``ID`` the message id echoed from the command (0–99, read as one or two
digits). ``#`` lines are info messages, ``!`` lines alerts; a reply longer than a packet
ends in ``\\`` and goes on in ``#<DD> <A> [<ID>] cont <more>`` packets. ``CC`` is the LRC:
the two's complement of the byte sum (mod 256) of everything between the leading marker
and the ``:``, as two upper-case hex digits. A device checks a command's ``CC`` whenever
one is sent (a bad one: no reply at all) but puts one on its own messages only with its
setting ``comm.checksum`` = 1 (default 0).

The flag field shows only the most urgent active flag (:data:`WARNING_FLAGS`): ``--``
none, ``F*`` faults, ``W*`` warnings (``WR`` no reference: ``home`` first; ``WL`` limit
sensor hit), ``N*`` notices (``NI`` move interrupted, ``NC`` manual knob); ``WT``
(controller hot) thus hides ``NI``, and ``WR`` hides every notice. The ``warnings``
command lists them all (``NN F1 F2 …``); ``warnings clear`` lists them and clears the
latched ones (:data:`STALE_NOTICE_FLAGS`), never ``WR`` (homing clears it). ``RJ`` replies
carry the reason (``BADDATA``, ``BADCOMMAND``, ``BADAXIS``, ``AGAIN``, ``DEVICEONLY``, …)
as data.

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
from dataclasses import dataclass

from mehs.errors import DeviceError

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

#: Latched flags that stay set, after whatever raised them, until ``warnings clear``: the
#: notices (``N*``) and the limit-sensor warning ``WL``. Left by a stop, the knob or another
#: program before a session, they say nothing about the next move. ``WR`` is not among
#: them (only homing sets a reference), nor are the faults (``F*``: the mechanics need a look
#: first) or the warnings that follow a live condition (``WT`` hot, ``WV`` supply, …).
STALE_NOTICE_FLAGS = ("WL",) + tuple(f for f in WARNING_FLAGS if f.startswith("N"))

_REPLY_RE = re.compile(
    r"^@(?P<dev>\d{2}) (?P<axis>\d+) (?:(?P<id>\d{1,2}) )?(?P<reply>OK|RJ) "
    r"(?P<status>IDLE|BUSY) (?P<flag>[-A-Z]{2}) (?P<data>.*?)(?::(?P<cc>[0-9A-F]{2}))?$")
_INFO_RE = re.compile(r"^#(?P<dev>\d{2}) (?P<axis>\d+) (?:(?P<id>\d{1,2}) )?(?P<data>.*?)"
                      r"(?::(?P<cc>[0-9A-F]{2}))?$")
_CHECKSUM_TAIL_RE = re.compile(r":[0-9A-F]{2}$")
_CONT_RE = re.compile(r"cont(?: +(.*))?")


class ZaberProtocolError(DeviceError):
    """A reply that does not follow the protocol (garbled, wrong device, bad checksum)."""


def lrc(body: bytes) -> int:
    """Zaber checksum of ``body`` (the bytes between ``/``, ``@``, ``#`` or ``!`` and ``:``)."""
    return (-sum(body)) & 0xFF


def has_checksum(text: str) -> bool:
    """Whether a message line (terminator stripped) ends in ``:CC``."""
    return _CHECKSUM_TAIL_RE.search(text) is not None


def _message(marker: bytes, parts: list[str], checksum: bool, end: bytes) -> bytes:
    body = " ".join(parts).encode("ascii")
    if checksum:
        body += b":" + f"{lrc(body):02X}".encode("ascii")
    return marker + body + end


def format_command(device: int, axis: int, command: str, *, checksum: bool = False,
                   msg_id: int | None = None) -> bytes:
    """Bytes of one command, e.g. ``format_command(1, 1, "move abs 1000") == b"/1 1 move abs 1000\\n"``."""
    parts = [str(int(device)), str(int(axis))]
    if msg_id is not None:
        parts.append(f"{int(msg_id) % 100:02d}")
    if command:
        parts.append(command)
    return _message(b"/", parts, checksum, b"\n")


def format_reply(device: int, axis: int, ok: bool, busy: bool, flag: str, data: str, *,
                 checksum: bool = False, msg_id: int | None = None) -> bytes:
    """Bytes of one reply (used by the simulator and by tests)."""
    parts = [f"{int(device):02d}", str(int(axis))]
    if msg_id is not None:
        parts.append(f"{int(msg_id) % 100:02d}")
    parts += ["OK" if ok else "RJ", "BUSY" if busy else "IDLE", flag, data]
    return _message(b"@", parts, checksum, b"\r\n")


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


def continuation_text(data: str) -> str | None:
    """The text an info message's data continues a reply with (``"cont WR NI"`` → ``"WR NI"``;
    a trailing ``\\`` means more packets follow), or None when it is not a ``cont`` packet."""
    m = _CONT_RE.fullmatch(data)
    return None if m is None else (m[1] or "").strip()


def parse_warnings(data: str, name: str | None = None) -> list[str]:
    """The flags of a ``warnings`` reply's data ``"NN F1 F2 …"`` (count, then the flags).

    Raises
    ------
    ZaberProtocolError
        When the data is empty, the count is not a number or does not match the list
        (``name``, the port, is named in the message).
    """
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


def format_warnings(flags) -> str:
    """The data of a ``warnings`` reply listing ``flags`` (``"02 NI WR"``; ``"00"`` for none)."""
    flags = list(flags)
    return f"{len(flags):02d}" + "".join(" " + f for f in flags)
