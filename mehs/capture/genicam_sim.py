"""A simulated line-scan hyperspectral camera served over real GigE Vision on loopback.

Aravis's fake GigE Vision camera (``ArvGvFakeCamera``) answers GVCP (control)
and sends GVSP (stream) on 127.0.0.1 exactly as a camera on the wire; its
GenICam XML is :func:`mehs.capture.genicam_xml.genicam_xml` (a line-scan HS
camera: Width = samples, Height = bands, Mono12/Mono16/packed, ExposureTime,
software trigger, shutter, spectral calibration). Each frame is filled from
the mehs sensor model (:class:`~mehs.capture.sensor.SensorModel`: QE, photon
and read noise, dark current, 12-bit ADC) looking at the world line under the
simulated stage (:class:`~mehs.capture.simdevice.SimWorld`, shared with the
simulated Zaber stage on TCP).

A stationary stage gives the frame :func:`~mehs.capture.simulate.simulate_bracket`
gives (same noise keys), so a step-mode capture over GigE Vision equals the
serial one byte for byte. While the stage moves, a frame integrates over its
exposure the world lines the slit passes (the world being a raster of lines
one pitch apart, as for the serial simulator; five sub-intervals).

Free-running frames keep a hardware frame clock: frame after frame is exposed on
the ticks of ``AcquisitionFrameRate`` even when the host stalls the fake camera's
thread; frames exposed meanwhile wait in an on-board buffer and are sent, late
but with their exposure timestamps, as soon as the thread runs again (as a real
camera's frame buffer drains after the link stalls).

Facts this module relies on (Aravis 0.8): the fill-pattern callback must be
installed through ctypes with a kept-alive ``CFUNCTYPE`` (PyGObject frees a
Python callback at once); inside it ``arv_buffer_get_data`` reports size 0,
so the frame size comes from the registers (the fake camera allocated
``Width·Height·bpp/8`` at acquisition start).

Faults (``camera:KIND@N[xCOUNT][/Tms]``, N = 1-based frame count; with ``/Tms`` only
frames exposed for T ms are counted, so that a fault lands in a chosen exposure of a
bracket however many frames a free-running continuous scan took before it):
``unplug`` — the camera disappears at frame N (GVCP and GVSP stop);
``incomplete`` — frame N's data packets are dropped on the way (the
receiver gets a leader and trailer only: an incomplete buffer);
``pixfmt`` — from frame N on the camera sends Mono8 frames (a
misconfigured camera); ``late`` — frame N is held on the way and delivered just
before the camera's next frame (with ``x2`` frames N and N+1 each come one
frame late: in a step scan the first trigger of a line times out, its frame is
taken by the retry, and the retry's own frame arrives after the next line's
trigger — the stale frame a driver must recognise). Stage faults are those of :mod:`mehs.capture.simdevice`.
"""

from __future__ import annotations

import ctypes
import re
import shutil
import struct
import sys
import tempfile
import threading
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from mehs.capture import genicam_xml as gx
from mehs.capture import pixfmt
from mehs.capture.gvcp_lock import GvcpPortLock
from mehs.capture.aravis import import_aravis
from mehs.capture.scene import Scene
from mehs.capture.sensor import SensorModel, exposure_seed_for
from mehs.capture.simdevice import SimStage, SimWorld
from mehs.capture.simserver import DeviceServer
from mehs.capture.simulate import motion_phase, world_radiance_line
from mehs.errors import DeviceError, InputError

GV_FAULT_KINDS = ("unplug", "incomplete", "pixfmt", "late")
_GV_RE = re.compile(r"^camera:(unplug|incomplete|pixfmt|late)@(\d+)(?:x(\d+))?(?:/(\d+(?:\.\d+)?)ms)?$")
#: Trigger-mode polling rate of the fake camera (Aravis's default, 25 Hz, caps step scans at ~24 lines/s).
TRIGGER_POLL_HZ = 2000.0
#: Frames the simulated camera's on-board buffer holds: exposed on its frame clock while the host
#: stalled the simulator's thread, and sent as soon as it runs again. Past this, frames are lost.
FRAME_BUFFER = 128
#: Wake-up period (µs) of the fake camera's thread while buffered frames wait to be sent.
CATCH_UP_US = 1000


@dataclass(frozen=True)
class GvFault:
    kind: str
    at: int
    count: int = 1
    #: count only the frames of this exposure time (µs); None: every frame
    exposure_us: int | None = None

    def fires(self, n: int) -> bool:
        return self.at <= n < self.at + self.count


def split_faults(spec: str | None) -> tuple[list[GvFault], str]:
    """GigE Vision camera faults, and the rest of the spec (stage faults) for :class:`SimWorld`."""
    gv, rest = [], []
    for item in re.split(r"[,\s]+", (spec or "").strip()):
        if not item:
            continue
        m = _GV_RE.match(item)
        if m:
            if int(m[2]) < 1 or int(m[3] or 1) < 1:
                raise InputError(f"bad fault {item!r}: N and COUNT start at 1")
            exp_us = None if m[4] is None else round(float(m[4]) * 1000.0)
            if exp_us is not None and exp_us < 1:
                raise InputError(f"bad fault {item!r}: the exposure time must be at least 1 µs")
            gv.append(GvFault(m[1], int(m[2]), int(m[3] or 1), exp_us))
        elif item.startswith("camera:"):
            raise InputError(f"bad GigE Vision camera fault {item!r}: use camera:KIND@N[xCOUNT][/Tms] with "
                             f"KIND one of {', '.join(GV_FAULT_KINDS)}")
        else:
            rest.append(item)
    return gv, ",".join(rest)


def _swept_radiance(scene: Scene, u0: float, u1: float, phase: float) -> np.ndarray:
    """Mean radiance ``(samples, bands)`` the slit sees while it sweeps from line ``u0`` to ``u1``.

    The world is a raster of lines one pitch apart (as for the serial simulator,
    which shows the line nearest the stage position): the exposure is split into
    five equal sub-intervals, each seeing the line nearest the slit then.
    """
    acc = None
    for u in np.linspace(u0, u1, 5):
        r = world_radiance_line(scene, int(np.floor(u + 0.5)), phase).astype(np.float64)
        acc = r if acc is None else acc + r
    return (acc / 5.0).astype(np.float32)


_FILL = ctypes.CFUNCTYPE(None, ctypes.c_void_p, ctypes.c_void_p, ctypes.c_uint32, ctypes.c_uint32,
                         ctypes.c_uint32)


def _libaravis():
    lib = ctypes.CDLL("libaravis-0.8.so.0")
    lib.arv_buffer_get_data.restype = ctypes.c_void_p
    lib.arv_buffer_get_data.argtypes = [ctypes.c_void_p, ctypes.POINTER(ctypes.c_size_t)]
    lib.arv_buffer_get_timestamp.restype = ctypes.c_uint64
    lib.arv_buffer_get_timestamp.argtypes = [ctypes.c_void_p]
    lib.arv_buffer_set_timestamp.restype = None
    lib.arv_buffer_set_timestamp.argtypes = [ctypes.c_void_p, ctypes.c_uint64]
    lib.arv_fake_camera_set_fill_pattern.restype = None
    lib.arv_fake_camera_set_fill_pattern.argtypes = [ctypes.c_void_p, _FILL, ctypes.c_void_p]
    return lib


def _gobject_pointer(obj) -> int:
    pyapi = ctypes.pythonapi
    pyapi.PyCapsule_GetPointer.restype = ctypes.c_void_p
    pyapi.PyCapsule_GetPointer.argtypes = [ctypes.py_object, ctypes.c_char_p]
    return pyapi.PyCapsule_GetPointer(obj.__gpointer__, None)


class GenicamSimCamera:
    """The simulated HS camera on Aravis's fake GigE Vision camera (127.0.0.1, GVCP port 3956).

    Parameters
    ----------
    world
        Shared scene, sensor and stage state.
    pixel_format, pixel_formats
        Initial PixelFormat and the entries the XML offers.
    shutter
        Whether the camera has a ``Shutter`` feature; without one, dark
        references need the lens capped (:attr:`lens_capped`, set by the
        ``--dark-prompt`` hook in tests).
    faults
        :class:`GvFault` list or spec string.
    max_frame_rate
        Highest ``AcquisitionFrameRate`` (Hz). Every frame is computed in Python
        (about 1 ms for 64 × 204); 100 Hz keeps a loaded two-core host on time.
    link_delay_ms
        Every GVSP packet reaches the receiver this much later (a slow link; 0: direct).
    start_delay_ms
        The sensor's first exposure comes this long after AcquisitionStart (a camera
        that settles its sensor first); a sequence gives each acquisition its own,
        the last repeating. The fake camera's one thread waits it out, and answers no
        GVCP meanwhile: keep it under the host's wait for a first frame plus Aravis's
        ~2.5 s of GVCP retries, or the AcquisitionStop of a rejected pass times out and
        the camera reads as unplugged (a real camera answers while it settles).
    port_wait_s
        Seconds to wait for another process's simulated camera to free GVCP port
        3956 (default: environment ``MEHS_GVCP_WAIT_S``, else 0 — fail at once);
        see :class:`~mehs.capture.gvcp_lock.GvcpPortLock`.
    """

    def __init__(self, world: SimWorld, *, serial: str = "MEHS0001", pixel_format: str = "Mono12",
                 pixel_formats: tuple[str, ...] = ("Mono12", "Mono16", "Mono12Packed", "Mono12p"),
                 shutter: bool = True, faults: list[GvFault] | str | None = None,
                 interface: str | None = None, max_frame_rate: float = 100.0,
                 link_delay_ms: float = 0.0, port_wait_s: float | None = None,
                 start_delay_ms: float | tuple[float, ...] = 0.0):
        self.Aravis, _ = import_aravis()
        self.world = world
        self.serial = serial
        self.faults = split_faults(faults)[0] if isinstance(faults, (str, type(None))) else list(faults)
        if pixel_format not in pixel_formats:
            raise InputError(f"pixel format {pixel_format} is not among the offered {pixel_formats}")
        self.pixel_format, self.pixel_formats, self.shutter = pixel_format, tuple(pixel_formats), shutter
        self.interface = interface or self.Aravis.GV_FAKE_CAMERA_DEFAULT_INTERFACE
        self.link_delay_s = float(link_delay_ms) / 1000.0
        delays = start_delay_ms if isinstance(start_delay_ms, (tuple, list)) else (start_delay_ms,)
        self.start_delays_s = [float(d) / 1000.0 for d in delays] or [0.0]
        self.acquisitions = 0
        self._port_lock = GvcpPortLock(self.interface, port_wait_s)
        self.lens_capped = False
        self.frames = 0
        self._fault_frames = [0] * len(self.faults)   # frames each fault has counted
        self._drop: set[int] = set()             # frame numbers an incomplete fault drops
        self._late: set[int] = set()             # frame numbers a late fault holds back
        self.fired: list[tuple[int, str]] = []
        self._next_tick: int | None = None       # the frame clock (ns): see _frame_clock
        self._tick_period = 0
        self.buffer_overflows = 0
        self.unplugged = threading.Event()
        self.errors: list[str] = []
        self._gv = None
        self._relay = None
        self._tmp = Path(tempfile.mkdtemp(prefix="mehs-gv-"))
        self.xml_path = self._tmp / "mehs-sim-hs.xml"
        self.xml_path.write_text(gx.genicam_xml(samples=world.samples, bands=world.bands,
                                                pixel_formats=pixel_formats, shutter=shutter,
                                                max_frame_rate=max_frame_rate))
        self._cb = _FILL(self._fill)   # kept alive for as long as the fake camera may call it
        self._lib = _libaravis()
        wl = np.asarray(world.scene.wavelengths, np.float64)
        self.coefficients = np.polyfit(np.arange(wl.size, dtype=np.float64), wl, 2)  # A, B, C

    @property
    def url(self) -> str:
        return "aravis://127.0.0.1"

    # ------------------------------------------------------------ lifecycle
    def start(self) -> "GenicamSimCamera":
        self._port_lock.acquire()     # held until close(): see GvcpPortLock
        try:
            return self._start()
        except BaseException:
            self._release()
            raise

    def _start(self) -> "GenicamSimCamera":
        # The fill callback needs the GIL within a frame period; CPython's default 5 ms
        # switch interval would make a busy host thread skip frames of the simulated camera.
        self._switch = sys.getswitchinterval()
        sys.setswitchinterval(min(self._switch, 0.0005))
        # The fake camera is held by the object alone, never by a local: stop() disposes it
        # when anything below fails, and a local named by the failure's traceback kept it
        # serving the GVCP port (a disposed GvFakeCamera closes its socket when finalised)
        # for as long as the caller held the error: this process's next simulator was refused.
        self._gv = self.Aravis.GvFakeCamera.new_full(self.interface, self.serial,
                                                     str(self.xml_path))
        if self._gv is None or not self._gv.is_running():
            raise DeviceError(f"cannot serve the simulated GigE Vision camera on {self.interface} "
                              "(no such interface?)", self.interface)
        self._fc = self._gv.get_fake_camera()
        self._program(self._fc)
        self._lib.arv_fake_camera_set_fill_pattern(_gobject_pointer(self._fc), self._cb, None)
        if any(f.kind in ("incomplete", "late") for f in self.faults) or self.link_delay_s > 0:
            from mehs.capture.gvrelay import StreamRelay

            self._relay = StreamRelay(self._fc, drop=self._drop_frame,
                                      hold=self._late.__contains__,
                                      delay_s=self.link_delay_s).start()
        return self

    def _program(self, fc) -> None:
        """The fake camera's registers: sensor, format, timing, wavelength polynomial, identity."""
        fc.set_trigger_frequency(TRIGGER_POLL_HZ)
        w = self.world
        reg = fc.write_register
        reg(gx.REG_SENSOR_WIDTH, w.samples)
        reg(gx.REG_SENSOR_HEIGHT, w.bands)
        reg(gx.REG_WIDTH, w.samples)
        reg(gx.REG_HEIGHT, w.bands)
        reg(gx.REG_PIXEL_FORMAT, pixfmt.PIXEL_FORMATS[self.pixel_format])
        reg(gx.REG_DYNAMIC_RANGE_MAX, (1 << w.sensor.bit_depth) - 1)
        reg(gx.REG_SHUTTER, 1)
        reg(gx.REG_FRAME_PERIOD_US, 10000)
        reg(gx.REG_WAKE_PERIOD_US, 10000)
        for addr, v in zip((gx.REG_WL_A, gx.REG_WL_B, gx.REG_WL_C), self.coefficients):
            self._write_double(fc, addr, float(v))
        self._write_double(fc, gx.REG_TEMPERATURE, w.temperature())
        for off, text in ((0x48, "MEHS"), (0x68, "SIM-HS"), (0x88, "1.0")):
            raw = text.encode("ascii")[:31] + b"\0"
            for i in range(0, len(raw), 4):
                reg(off + i, struct.unpack(">I", raw[i:i + 4].ljust(4, b"\0"))[0])

    def stop(self) -> None:
        """Stop serving (the camera is "unplugged"); safe to call twice."""
        if self._relay is not None:
            self._relay.close()
            self._relay = None
        gv, self._gv = self._gv, None
        if gv is not None:
            self._fc = None
            gv.run_dispose()
            del gv
        self.unplugged.set()

    def _release(self) -> None:
        self.stop()
        if getattr(self, "_switch", None) is not None:
            sys.setswitchinterval(self._switch)
            self._switch = None
        # (not in stop(): an "unplugged" camera keeps the port until the test is done with it,
        # so that no other process's camera answers at its address meanwhile)
        self._port_lock.release()

    def close(self) -> None:
        self._release()
        shutil.rmtree(self._tmp, ignore_errors=True)

    def __enter__(self):
        return self.start()

    def __exit__(self, *exc):
        self.close()

    @staticmethod
    def _write_double(fc, addr: int, v: float) -> None:
        hi, lo = struct.unpack(">II", struct.pack(">d", v))
        fc.write_register(addr, hi)
        fc.write_register(addr + 4, lo)

    def _read(self, addr: int) -> int:
        ok, v = self._fc.read_register(addr)
        return int(v)

    def _drop_frame(self, frame_number: int) -> bool:
        # (the relay numbers frames as _fill_checked does, which runs before each is sent)
        return frame_number in self._drop

    # ------------------------------------------------------------ frames
    def _frame_clock(self, fc, ts_ns: int) -> int:
        """Exposure start (ns) of this free-running frame: the next tick of the frame clock.

        A hardware-timed camera exposes frame after frame on its clock whatever the
        host does; the fake camera's thread only wakes on multiples of its period, and
        on a busy host late, skipping the ticks it slept through (a stall of 0.1 s
        while the stage moved left lines without frames). So the frame clock is kept
        here: each frame takes the next tick, however late the thread woke, and while
        ticks have passed unsent the thread is woken every :data:`CATCH_UP_US` to send
        them — an on-board buffer of :data:`FRAME_BUFFER` frames draining after a stall.
        """
        period_us = max(1, self._read(gx.REG_FRAME_PERIOD_US))
        period_ns = period_us * 1000
        tick = ts_ns - ts_ns % period_ns          # the latest tick the thread woke after
        nxt = self._next_tick
        if nxt is None or self._tick_period != period_ns or nxt > tick:
            nxt = tick                            # a new acquisition or frame rate
        elif tick - nxt >= FRAME_BUFFER * period_ns:
            # the buffer was full: the oldest frames were overwritten, the newest
            # FRAME_BUFFER are still sent (a gap in the timestamps, as on a real camera)
            lost = (tick - nxt) // period_ns - (FRAME_BUFFER - 1)
            self.buffer_overflows += 1
            self.errors.append(f"frame buffer overflow: {lost} frames lost after a stall")
            nxt = tick - (FRAME_BUFFER - 1) * period_ns
        self._next_tick, self._tick_period = nxt + period_ns, period_ns
        behind = self._next_tick <= time.time_ns()
        wake = CATCH_UP_US if behind else period_us
        if self._read(gx.REG_WAKE_PERIOD_US) != wake:
            fc.write_register(gx.REG_WAKE_PERIOD_US, wake)
        return nxt

    def _fill(self, buf, _data, exposure_us, _gain, pixel_format) -> None:
        # Runs on the fake camera's thread: never let an exception cross into C.
        try:
            self._fill_checked(buf, int(exposure_us), int(pixel_format))
        except Exception as exc:  # pragma: no cover - reported through .errors
            self.errors.append(f"{type(exc).__name__}: {exc}")

    def _fill_checked(self, buf, exposure_us: int, code: int) -> None:
        fc = self._fc
        if fc is None:
            return
        self.frames += 1
        n = self.frames
        for k, f in enumerate(self.faults):
            # the fake camera keeps the exposure in whole µs: a time within 1 µs is the same
            if f.exposure_us is not None and abs(exposure_us - f.exposure_us) > 1:
                continue
            self._fault_frames[k] += 1
            if not f.fires(self._fault_frames[k]):
                continue
            if f.kind == "incomplete":
                self._drop.add(n)
            elif f.kind == "late":
                self._late.add(n)
            else:
                self.fired.append((n, f.kind))
                if f.kind == "unplug":
                    # dispose from another thread: this one is the camera's own
                    threading.Thread(target=self.stop, daemon=True).start()
                    return
                fc.write_register(gx.REG_PIXEL_FORMAT, pixfmt.PIXEL_FORMATS["Mono8"])
        w = self.world
        t_ms = exposure_us / 1000.0
        ts_ns = int(self._lib.arv_buffer_get_timestamp(buf))
        if self._read(gx.REG_ACQUISITION) == 1:
            # AcquisitionStart wrote 1: a new acquisition, whose frame clock starts afresh.
            # (Any non-zero value keeps the fake camera streaming; 2 marks this one as seen.)
            fc.write_register(gx.REG_ACQUISITION, 2)
            self._next_tick = None
            delay = self.start_delays_s[min(self.acquisitions, len(self.start_delays_s) - 1)]
            self.acquisitions += 1
            if delay > 0:
                # the camera's own thread waits: no frame until the sensor has settled,
                # and its frame clock starts then
                time.sleep(delay)
                ts_ns += int(delay * 1e9)
        if self._read(0x300) == 0:   # TriggerMode Off: free-running on the frame clock
            ts_ns = self._frame_clock(fc, ts_ns)
            self._lib.arv_buffer_set_timestamp(buf, ts_ns)
        ts = ts_ns / 1e9
        with w.lock:
            now = time.monotonic() - (time.time() - ts)
            p0, p1 = w.position_at(now), w.position_at(now + t_ms / 1000.0)
            shutter_open = self._read(gx.REG_SHUTTER) == 1 and not self.lens_capped
            w.lines_acquired += 1
            temp = w.temperature()
        scene, phase = w.scene, (motion_phase(t_ms) if w.scene.moving else 0)
        u0, u1 = p0 / w.pitch, p1 / w.pitch
        if abs(u1 - u0) < 1e-9 and abs(u0 - round(u0)) < 1e-9:
            line = int(round(u0))   # stationary on a line: exactly the serial simulator's frame
            rad, seed = world_radiance_line(scene, line, phase), exposure_seed_for(t_ms)
        else:
            line = int(round((u0 + u1) / 2))
            rad = _swept_radiance(scene, u0, u1, phase)
            seed = exposure_seed_for(t_ms) ^ (n * 0x9E3779B1 & 0x7FFFFFFF)
        z = w.sensor.expose_line(rad, t_ms, exposure_seed=seed, line_index=line,
                                 shutter_open=shutter_open, wavelengths=scene.wavelengths)
        self._write_double(fc, gx.REG_TEMPERATURE, temp)
        name = pixfmt.name_of(code)
        # the sensor is 12-bit; Mono8 (the pixfmt fault) keeps the top 8 bits
        px = (z >> 4) if name == "Mono8" else z
        data = pixfmt.pack(px.T, code)            # frame rows = bands, columns = samples
        size = ctypes.c_size_t(0)
        ptr = self._lib.arv_buffer_get_data(buf, ctypes.byref(size))  # size is 0 here: see module doc
        if ptr:
            ctypes.memmove(ptr, data, len(data))


class SimGenicamDevices:
    """Simulated Zaber stage (TCP) + simulated GigE Vision HS camera sharing one world.

    Use as a context manager; :attr:`stage_url` and :attr:`camera_url` are what
    ``mehs capture --stage … --camera …`` opens. ``comm_checksum`` starts the stage with
    ``comm.checksum`` = 1 (checksums on its replies), as :class:`~mehs.capture.simdevice.SimDevices`.
    """

    def __init__(self, scene: Scene, sensor: SensorModel | None = None, *, faults: str | None = None,
                 pitch: int = 64, host: str = "127.0.0.1", port: int = 0, start_homed: bool = False,
                 speed: float = 4e6, comm_checksum: bool = False, **camera_options):
        gv, rest = split_faults(faults)
        self.world = SimWorld(scene, sensor or SensorModel(), pitch=pitch, faults=rest,
                              start_homed=start_homed, speed=speed)
        self.stage = SimStage(self.world, comm_checksum=comm_checksum)
        self.server = DeviceServer(self.stage.handle, host=host, port=port, name="stage")
        self._serving = False
        try:
            self.camera = GenicamSimCamera(self.world, faults=gv, **camera_options)
        except BaseException:
            self.server.sock.close()   # bound above: no object is left to close() it
            raise

    @property
    def stage_url(self) -> str:
        return self.server.url

    @property
    def camera_url(self) -> str:
        return self.camera.url

    @property
    def scene_lines(self) -> int:
        return self.world.scene.radiance.shape[0]

    def start(self) -> "SimGenicamDevices":
        self.camera.start()
        try:
            self.server.start()
        except BaseException:
            # used as a context manager, a failed start has no __exit__: the started camera
            # would keep this process's GVCP port, and every later simulator be refused
            self.close()
            raise
        self._serving = True
        return self

    def close(self) -> None:
        """Stop both devices and free their ports; safe at any point (before or after a
        failed :meth:`start`, and twice)."""
        try:
            if self._serving:
                self.server.close()
            else:
                # DeviceServer.close() joins its thread, which raises for one never started
                self.server.sock.close()
        finally:
            self.camera.close()

    def __enter__(self) -> "SimGenicamDevices":
        return self.start()

    def __exit__(self, *exc) -> None:
        self.close()
