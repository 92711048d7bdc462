"""Simulated stage + camera that speak the real protocols over loopback TCP (or a pty).

The production drivers (:mod:`mehs.capture.zaber`, :mod:`mehs.capture.camera`)
talk to these exactly as to hardware, through ``socket://127.0.0.1:PORT``
(pyserial) or a pseudo-terminal. Both devices share one :class:`SimWorld`:
the stage position selects the world line the camera sees
(``line = round(position / pitch)``; scene lines, then a gap, then a white
tile — see :mod:`mehs.capture.simulate`), and the camera exposes it with the
:class:`~mehs.capture.sensor.SensorModel`, the noise keyed by (sensor seed,
integration time, line, shutter) — so a capture through the devices equals
:func:`~mehs.capture.simulate.simulate_bracket` byte for byte.

Fault injection is deterministic: a fault spec such as
``"camera:garble@40,stage:disconnect@10x2"`` fires on the 40th line
acquisition of the camera (``READ?``/``INIT``) and on the 10th and 11th motion
command of the stage (``home``/``move``). Kinds: ``timeout`` (no reply),
``garble`` (corrupted bytes), ``partial`` (half a reply, no terminator),
``disconnect`` (the connection drops before the reply), ``again`` (stage:
``RJ AGAIN``), ``fault`` (stage: stalls half-way and raises ``FS``, which
persists until ``warnings clear``), ``late`` (the reply comes after the host's
timeout, just before the next reply — a slow link).
"""

from __future__ import annotations

import re
import threading
import time
from collections import deque
from dataclasses import dataclass

import numpy as np

from mehs.capture.camera import encode_line
from mehs.capture.scene import Scene
from mehs.capture.sensor import SensorModel, exposure_seed_for
from mehs.capture.simulate import (WHITE_TILE_LINES, motion_phase, white_tile_first_line,
                                   world_radiance_line)
from mehs.capture.zaber_protocol import (STALE_NOTICE_FLAGS, WARNING_FLAGS, format_reply,
                                         format_warnings, lrc, speed_from_setting, speed_setting)
from mehs.capture.simserver import DeviceServer, PtyServer
from mehs.errors import InputError

FAULT_KINDS = ("timeout", "garble", "partial", "disconnect", "again", "fault", "late")
_FAULT_RE = re.compile(r"^(stage|camera):([a-z]+)@(\d+)(?:x(\d+))?$")


@dataclass(frozen=True)
class Fault:
    """Inject ``kind`` on the ``at``-th (1-based) eligible command of ``device``, ``count`` times."""

    device: str
    kind: str
    at: int
    count: int = 1


def parse_faults(spec: str | None) -> list[Fault]:
    """Parse ``"camera:garble@40,stage:disconnect@10x2"`` (comma or space separated)."""
    out = []
    for item in re.split(r"[,\s]+", (spec or "").strip()):
        if not item:
            continue
        m = _FAULT_RE.match(item)
        if not m or m[2] not in FAULT_KINDS:
            raise InputError(f"bad fault {item!r}: use DEVICE:KIND@N[xCOUNT] with DEVICE stage|camera "
                             f"and KIND one of {', '.join(FAULT_KINDS)}")
        if m[2] in ("again", "fault") and m[1] != "stage":
            raise InputError(f"fault {m[2]!r} applies to the stage only")
        count = int(m[4] or 1)
        if int(m[3]) < 1 or count < 1:
            raise InputError(f"bad fault {item!r}: N and COUNT start at 1")
        out.append(Fault(m[1], m[2], int(m[3]), count))
    return out


class FaultPlan:
    """Counts eligible commands per device and says which fault (if any) to inject."""

    def __init__(self, faults: list[Fault] | str | None = None):
        self.faults = parse_faults(faults) if isinstance(faults, (str, type(None))) else list(faults)
        self.counters = {"stage": 0, "camera": 0}
        self.fired: list[tuple[str, int, str]] = []
        self._lock = threading.Lock()

    def next(self, device: str) -> str | None:
        with self._lock:
            self.counters[device] += 1
            n = self.counters[device]
            for f in self.faults:
                if f.device == device and f.at <= n < f.at + f.count:
                    self.fired.append((device, n, f.kind))
                    return f.kind
        return None


class SimWorld:
    """Shared state of the simulated stage and camera.

    Parameters
    ----------
    scene, sensor
        What the camera sees and how it records it.
    pitch
        Stage microsteps per scanned line.
    speed
        Stage speed (microsteps/s); moves take ``distance / speed``.
    start_homed
        Whether the stage starts homed (a real one powers up with ``WR``).
    """

    def __init__(self, scene: Scene, sensor: SensorModel, *, pitch: int = 64, speed: float = 4e6,
                 faults: FaultPlan | str | None = None, start_homed: bool = False,
                 realtime: bool = False):
        self.scene, self.sensor = scene, sensor
        self.pitch, self.speed = int(pitch), float(speed)
        self.plan = faults if isinstance(faults, FaultPlan) else FaultPlan(faults)
        self.lock = threading.RLock()
        self.realtime = realtime
        lines = scene.radiance.shape[0]
        self.limit_max = (white_tile_first_line(lines) + WHITE_TILE_LINES + 16) * self.pitch
        # stage
        self.homed = bool(start_homed)
        self.pos = 0.0
        self._move: tuple[float, float, float, float] | None = None  # from, to, t0, duration
        self._stall_at: float | None = None
        # recent moves [t0, from, to, duration, stall_at, t_stopped, stopped_at], so that a
        # camera delivering frames from its buffer knows where the stage was when each was exposed
        self._moves: deque[list] = deque(maxlen=64)
        self._homing = False        # WR clears when homing reaches the home sensor, not before
        self.flags: set[str] = set()
        self.maxspeed = speed_setting(self.speed)    # the device's unit, as a real stage's
        # camera
        self.t_ms = 10.0
        self.shutter_open = True
        self.last_line: np.ndarray | None = None
        self.lines_acquired = 0
        self.errors: deque[tuple[int, str]] = deque(maxlen=32)
        self.samples, self.bands = scene.radiance.shape[1:]

    # ------------------------------------------------------------ stage physics
    def _update(self) -> None:
        if self._move is None:
            return
        p0, p1, t0, dur = self._move
        frac = 1.0 if dur <= 0 else min(1.0, (time.monotonic() - t0) / dur)
        if self._stall_at is not None and frac >= self._stall_at:
            self.pos = p0 + (p1 - p0) * self._stall_at
            self._move, self._stall_at, self._homing = None, None, False
            self.flags.add("FS")
            return
        self.pos = p0 + (p1 - p0) * frac
        if frac >= 1.0:
            self.pos = p1
            self._move = None
            if self._homing:
                self.homed, self._homing = True, False

    def busy(self) -> bool:
        self._update()
        return self._move is not None

    def position(self) -> int:
        self._update()
        return int(round(self.pos))

    def start_move(self, target: float, *, stall: bool = False, homing: bool = False) -> None:
        self._update()
        self._homing = homing
        dur = abs(target - self.pos) / speed_from_setting(max(self.maxspeed, 1))
        self._move = (self.pos, float(target), time.monotonic(), dur)
        self._stall_at = 0.5 if stall else None
        self._moves.append([self._move[2], self.pos, float(target), dur, self._stall_at, None, None])

    def stop(self) -> None:
        if self.busy():
            self._move, self._homing = None, False
            self.flags.add("NI")
            if self._moves:
                self._moves[-1][5:] = [time.monotonic(), self.pos]

    def position_at(self, t_mono: float) -> float:
        """Stage position (microsteps, unrounded) at monotonic time ``t_mono``, past or present.

        Past times come from the record of recent moves (a stop freezes the position
        where it happened; a stall fault freezes it half-way).
        """
        for t0, p0, p1, dur, stall_at, t_stop, p_stop in reversed(self._moves):
            if t0 > t_mono:
                continue
            if t_stop is not None and t_mono >= t_stop:
                return float(p_stop)
            frac = 1.0 if dur <= 0 else min(1.0, max(0.0, (t_mono - t0) / dur))
            if stall_at is not None:
                frac = min(frac, stall_at)
            return p0 + (p1 - p0) * frac
        # before every recorded move: where the oldest began (or the stage never moved)
        return float(self._moves[0][1]) if self._moves else float(self.pos)

    def world_line(self) -> int:
        return int(round(self.position() / self.pitch))

    def flag(self) -> str:
        # the reply shows the highest-priority active flag (WR outranks the N* notices)
        active = set(self.warning_list())
        return next((f for f in WARNING_FLAGS if f in active), "--")

    def warning_list(self) -> list[str]:
        out = sorted(self.flags)
        if not self.homed:
            out = sorted(out + ["WR"])
        return out

    # ------------------------------------------------------------ camera physics
    def acquire(self) -> np.ndarray:
        line = self.world_line()
        t = self.t_ms
        rad = world_radiance_line(self.scene, line, motion_phase(t) if self.scene.moving else 0)
        if self.realtime:
            time.sleep(t / 1000.0)
        z = self.sensor.expose_line(rad, t, exposure_seed=exposure_seed_for(t), line_index=line,
                                    shutter_open=self.shutter_open, wavelengths=self.scene.wavelengths)
        self.last_line = z
        self.lines_acquired += 1
        return z

    def temperature(self) -> float:
        # warms up slowly with use, deterministic given the command sequence
        return 24.0 + 2.0 * (1.0 - np.exp(-self.lines_acquired / 4000.0))


# ---------------------------------------------------------------- protocol handlers
# device, axis and id are optional leading numbers ("/home" goes to every device, axis 0);
# each must be a whole word ("/1hi" is the command "1hi")
_CMD_RE = re.compile(r"^/(?:(?P<dev>\d+)(?![^ :])(?: +(?P<axis>\d+)(?![^ :])"
                     r"(?: +(?P<id>\d{1,2})(?![^ :]))?)?)? *(?P<cmd>[^:]*?) *"
                     r"(?::(?P<cc>[0-9A-Fa-f]{2}))?$")


class SimStage:
    """Zaber ASCII handler: one command line in, one reply (bytes) out, or ``None`` (ignored).

    ``comm_checksum`` is the device setting ``comm.checksum``: 1 puts a checksum on every
    reply (``mehs sim-device --comm-checksum``), as ``/set comm.checksum 1`` does; at 0 (a
    real device's default) a command's own checksum is checked but not echoed.
    """

    device_address = 1

    def __init__(self, world: SimWorld, *, comm_checksum: bool = False):
        self.w = world
        self.comm_checksum = 1 if comm_checksum else 0

    def handle(self, raw: bytes) -> tuple[bytes | None, str | None]:
        text = raw.decode("ascii", "replace").strip("\r\n")
        m = _CMD_RE.match(text)
        if not m:
            return None, None  # not a command: a Zaber device ignores it
        cs = m["cc"] is not None
        if cs:
            body = text[1:text.rindex(":")].encode("ascii", "replace")
            if lrc(body) != int(m["cc"], 16):
                return None, None  # bad checksum: ignored, the host will time out
        dev = int(m["dev"]) if m["dev"] else 0
        if dev not in (0, self.device_address):
            return None, None
        axis = int(m["axis"]) if m["axis"] else 0
        msg_id = int(m["id"]) if m["id"] else None
        cmd = (m["cmd"] or "").strip()
        w = self.w

        def reply(ok: bool, data: str = "0", flag: str | None = None) -> bytes:
            with w.lock:
                busy = w.busy()
                fl = flag or w.flag()
            return format_reply(self.device_address, axis, ok, busy, fl, data,
                                checksum=self.comm_checksum == 1, msg_id=msg_id)

        if axis not in (0, 1):
            return reply(False, "BADAXIS"), None
        words = cmd.split()
        with w.lock:
            if not words:
                return reply(True), None
            head = " ".join(words[:2]) if words[0] in ("move", "get", "set") else words[0]
            args = words[2:] if words[0] in ("move", "get", "set") else words[1:]
            if head in ("home", "move abs", "move rel"):
                fault = w.plan.next("stage")
                if fault == "again":
                    return reply(False, "AGAIN"), None
                if any(f.startswith("F") for f in w.flags):
                    return reply(False, "BADCOMMAND"), fault
                if head == "home":
                    if args:
                        return reply(False, "BADDATA"), fault
                    w.start_move(0, stall=fault == "fault", homing=True)
                    return reply(True), fault
                if len(args) != 1 or not re.fullmatch(r"-?\d+", args[0]):
                    return reply(False, "BADDATA"), fault
                if not w.homed:
                    return reply(False, "BADCOMMAND"), fault
                target = int(args[0]) + (w.position() if head == "move rel" else 0)
                if not 0 <= target <= w.limit_max:
                    return reply(False, "BADDATA"), fault
                # a new move leaves the notices as they are: NI, NC, WL stay latched until
                # 'warnings clear', so a stale one is still reported after this move
                w.start_move(target, stall=fault == "fault")
                return reply(True), fault
            if head == "get pos" and not args:
                return reply(True, str(w.position())), None
            if head == "get maxspeed" and not args:
                return reply(True, str(w.maxspeed)), None
            if head == "get limit.max" and not args:
                return reply(True, str(w.limit_max)), None
            if head in ("get comm.checksum", "set comm.checksum"):
                if axis != 0:
                    return reply(False, "DEVICEONLY"), None   # a device-scope setting
                if head == "get comm.checksum" and not args:
                    return reply(True, str(self.comm_checksum)), None
                if head == "get comm.checksum" or args not in (["0"], ["1"]):
                    return reply(False, "BADDATA"), None
                self.comm_checksum = int(args[0])
                return reply(True), None
            if head == "set maxspeed":
                if len(args) != 1 or not args[0].isdigit() or int(args[0]) < 1:
                    return reply(False, "BADDATA"), None
                w.maxspeed = int(args[0])
                return reply(True), None
            if head == "warnings" and args in ([], ["clear"]):
                data = format_warnings(w.warning_list())   # the flags before any clearing
                if args:
                    # the latched notices and the faults go (a fault is cleared only when
                    # asked, as on a real stage); WR stays: homing alone clears it
                    w.flags -= {f for f in w.flags if f in STALE_NOTICE_FLAGS or f.startswith("F")}
                return reply(True, data), None
            if head == "stop" and not args:
                w.stop()
                return reply(True), None
            return reply(False, "BADCOMMAND"), None


_SCPI_ERRORS = {-100: "Command error", -113: "Undefined header", -222: "Data out of range",
                -224: "Illegal parameter value", -230: "Data corrupt or stale"}


class SimCamera:
    """Line-scan camera protocol handler (docs/protocols.md)."""

    IDN = "MEHS,SIMLINE-{bands},SIM0001,1.0"
    T_MIN_MS, T_MAX_MS, T_STEP_MS = 0.01, 10000.0, 0.01

    def __init__(self, world: SimWorld):
        self.w = world

    def _err(self, code: int, detail: str = "") -> bytes:
        msg = _SCPI_ERRORS[code] + (f"; {detail}" if detail else "")
        self.w.errors.append((code, msg))
        return f'ERR {code},"{msg}"\n'.encode("ascii")

    def handle(self, raw: bytes) -> tuple[bytes | None, str | None]:
        text = raw.decode("ascii", "replace").strip("\r\n").strip()
        if not text:
            return None, None
        head, _, arg = text.partition(" ")
        head, arg = head.upper(), arg.strip()
        w = self.w
        with w.lock:
            if head in ("READ?", "INIT"):
                fault = w.plan.next("camera")
                z = w.acquire()
                return (encode_line(z) if head == "READ?" else b"OK\n"), fault
            if head == "FETC?":
                if w.last_line is None:
                    return self._err(-230, "no line acquired"), None
                return encode_line(w.last_line), None
            if head == "*IDN?":
                return (self.IDN.format(bands=w.bands) + "\n").encode(), None
            if head == "*RST":
                w.t_ms, w.shutter_open, w.last_line = 10.0, True, None
                w.errors.clear()
                return b"OK\n", None
            if head == "CONF:INT":
                try:
                    t = float(arg)
                except ValueError:
                    return self._err(-224, f"not a number: {arg!r}"), None
                if not (np.isfinite(t) and self.T_MIN_MS <= t <= self.T_MAX_MS):
                    return self._err(-222, f"integration time {arg} ms outside "
                                           f"{self.T_MIN_MS}..{self.T_MAX_MS}"), None
                # the line clock has a 10 µs step
                w.t_ms = round(round(t / self.T_STEP_MS) * self.T_STEP_MS, 6)
                return b"OK\n", None
            if head == "CONF:INT?":
                return f"{w.t_ms:.6g}\n".encode(), None
            if head == "SHUT":
                if arg.upper() not in ("OPEN", "CLOSE"):
                    return self._err(-224, f"shutter state {arg!r}"), None
                w.shutter_open = arg.upper() == "OPEN"
                return b"OK\n", None
            if head == "SHUT?":
                return (b"OPEN\n" if w.shutter_open else b"CLOSED\n"), None
            if head == "FORM:SHAP?":
                return f"{w.samples},{w.bands}\n".encode(), None
            if head == "SYST:WAV?":
                return (",".join(f"{v:.2f}" for v in w.scene.wavelengths) + "\n").encode(), None
            if head == "SYST:FWHM?":
                return (",".join(f"{v:.2f}" for v in w.scene.fwhm) + "\n").encode(), None
            if head == "SYST:BITS?":
                return f"{w.sensor.bit_depth}\n".encode(), None
            if head == "TEMP?":
                return f"{w.temperature():.2f}\n".encode(), None
            if head == "FRAT?":
                return f"{1000.0 / (w.t_ms + 0.5):.3f}\n".encode(), None
            if head == "SYST:ERR?":
                if w.errors:
                    code, msg = w.errors.popleft()
                    return f'{code},"{msg}"\n'.encode(), None
                return b'0,"No error"\n', None
            return self._err(-113, head), None


class SimDevices:
    """The simulated stage and camera, served on loopback TCP (``transport="tcp"``) or ptys.

    Use as a context manager; :attr:`stage_url` and :attr:`camera_url` are what
    the drivers open. ``comm_checksum`` starts the stage with ``comm.checksum`` = 1 (its
    replies carry checksums, for drivers run with ``checksum=True``).
    """

    def __init__(self, scene: Scene, sensor: SensorModel | None = None, *, faults: str | None = None,
                 pitch: int = 64, host: str = "127.0.0.1", port: int = 0, transport: str = "tcp",
                 start_homed: bool = False, speed: float = 4e6, comm_checksum: bool = False):
        self.world = SimWorld(scene, sensor or SensorModel(), pitch=pitch, faults=faults,
                              start_homed=start_homed, speed=speed)
        self.stage = SimStage(self.world, comm_checksum=comm_checksum)
        self.camera = SimCamera(self.world)
        if transport == "tcp":
            self.servers = [DeviceServer(self.stage.handle, host=host, port=port, name="stage"),
                            DeviceServer(self.camera.handle, host=host, port=port + 1 if port else 0,
                                         name="camera")]
        elif transport == "pty":
            self.servers = [PtyServer(self.stage.handle, name="stage"),
                            PtyServer(self.camera.handle, name="camera")]
        else:
            raise InputError(f"unknown transport {transport!r} (tcp or pty)")

    @property
    def stage_url(self) -> str:
        return self.servers[0].url

    @property
    def camera_url(self) -> str:
        return self.servers[1].url

    @property
    def scene_lines(self) -> int:
        return self.world.scene.radiance.shape[0]

    def start(self) -> "SimDevices":
        for s in self.servers:
            s.start()
        return self

    def close(self) -> None:
        for s in self.servers:
            s.close()

    def __enter__(self) -> "SimDevices":
        return self.start()

    def __exit__(self, *exc) -> None:
        self.close()
