"""GenICam camera driver (GigE Vision, USB3 Vision) through Aravis: line-scan hyperspectral cameras.

A line-scan hyperspectral camera (Specim FX10/FX17, Resonon Pika, …) sends one
*spectral frame* per scan line: ``Width`` = spatial samples, ``Height`` =
bands, pixel format Mono12 / Mono12Packed / Mono12p / Mono16. This driver
gives it the interface :class:`~mehs.capture.camera.LineCamera` has
(``shape``, ``wavelengths``, ``set_integration_time``, ``set_shutter``,
``read_line``, …), so :func:`~mehs.capture.session.capture_scene`,
auto-exposure, references, resume and provenance work unchanged, plus
:meth:`GenicamCamera.stream` for constant-velocity scans
(:mod:`mehs.capture.scan`).

Features used (GenICam SFNC): ``ExposureTime`` (µs), ``AcquisitionFrameRate`` (or the SFNC 1.x
spellings ``ExposureTimeAbs`` / ``AcquisitionFrameRateAbs`` many cameras keep:
:mod:`~mehs.capture.genicam_features`),
``AcquisitionMode``, ``TriggerSelector``/``TriggerMode``/``TriggerSource``/
``TriggerSoftware``, ``AcquisitionStart``/``AcquisitionStop``,
``BinningVertical``, ``PixelFormat``, ``PixelDynamicRangeMax``,
``DeviceTemperature``. Not standardised, hence configurable: the shutter
(default feature ``Shutter`` = ``Open``/``Closed``) and the spectral
calibration (features ``WavelengthCoefficientA/B/C`` of the vendor
polynomial λ = A·x² + B·x + C over the unbinned sensor row x, or a
calibration given by the user).

Reliability: a step-mode line is software-triggered; a timeout or an
incomplete / lost buffer (missing packets) is counted in :attr:`events` and
the line triggered again (same stage position) up to ``retries`` times; a
late frame of an earlier trigger, which may come after the stage moved on, is
recognised by its block id and arrival time, dropped and logged
(:class:`~mehs.capture.genicam_frames.TriggerLedger`); frames still on the way when a
free-running acquisition stops are awaited and dropped (:meth:`GenicamCamera._flush`);
a buffer whose pixel format or size does not match the configured frame
is a :class:`~mehs.errors.DeviceError` at once (a configuration fault, not a
transient one). A lost control channel ("camera unplugged") is
:class:`~mehs.errors.DeviceDisconnected`; the capture then stops and can be
resumed.

References
----------
EMVA, *GenICam Standard Features Naming Convention (SFNC) 2.7*, 2022.
AIA, *GigE Vision 2.0*, 2011. E. Pacaud, *Aravis 0.8 API reference*,
https://aravisproject.github.io/aravis/.
"""

from __future__ import annotations

import queue
import threading
import time
import weakref
from typing import Any, Callable

import numpy as np

from mehs.capture import pixfmt
from mehs.capture.aravis import SCHEMES, import_aravis
from mehs.capture.genicam_features import EXPOSURE_TIME, FRAME_RATE, FeatureAccess, gerror
from mehs.capture.genicam_frames import Frame, FrameStream, TriggerLedger
from mehs.capture.spectral_cal import polynomial_wavelengths
from mehs.errors import DeviceDisconnected, DeviceError, DeviceTimeout, InputError


__all__ = ["Frame", "FrameStream", "GenicamCamera"]   # Frame, FrameStream: re-exported


def _control_lost(camera: "weakref.ref[GenicamCamera]") -> Callable[..., None]:
    """The "control-lost" handler of the camera ``camera`` refers to (weakly: see
    :class:`GenicamCamera`); it runs on the device's heartbeat thread."""
    def on_lost(*_a: Any) -> None:
        cam = camera()
        if cam is not None:
            cam._control_lost = True

    return on_lost


_releases: "queue.SimpleQueue[tuple[list, float]]" = queue.SimpleQueue()
_release_lock = threading.Lock()
_release_thread: threading.Thread | None = None


def _release_elsewhere(held: list, delay_s: float = 0.0) -> None:
    """Drop the Aravis objects ``held`` on one release thread of the process: finalising a
    device stops (joins) its heartbeat thread and tells the camera over GVCP, which must
    happen neither on that thread nor on a thread the camera waits for."""
    global _release_thread
    try:
        with _release_lock:
            if _release_thread is None or not _release_thread.is_alive():
                _release_thread = threading.Thread(target=_release_loop, daemon=True,
                                                   name="mehs-genicam-release")
                _release_thread.start()
        _releases.put((list(held), delay_s))
    except Exception:      # noqa: BLE001 - interpreter shutdown: nothing left to protect
        pass
    held.clear()           # (the caller's references; the queue holds the objects now)


def _release_loop() -> None:
    while True:
        held, delay_s = _releases.get()
        if delay_s > 0:
            time.sleep(delay_s)
        held.clear()
        del held


class GenicamCamera(FeatureAccess):
    """Line-scan hyperspectral camera on Aravis (GigE Vision / USB3 Vision).

    Parameters
    ----------
    device_id
        Aravis device id (``Vendor-Model-Serial``), an IP address, or a serial.
    timeout
        Seconds to wait for a frame beyond its exposure and frame period.
    retries
        Re-triggers of a step-mode line after a timeout or an incomplete buffer.
    wavelengths
        Band centres (nm) from a calibration file; default: the camera's
        ``WavelengthCoefficientA/B/C`` features.
    dark_prompt
        Called with ``"close"`` / ``"open"`` when the camera has no shutter
        feature and the shutter must change (a person caps the lens); without it
        such a camera cannot take dark references.
    shutter_feature, shutter_values
        Enumeration feature and its ``(open, closed)`` entries.
    n_buffers
        Stream buffers queued to the receiver.
    frame_ids
        Tell a step-mode line's frame from a late one of an earlier trigger by
        block id (default); False for a camera whose ids do not increase (URL
        option ``?frame-ids=off``): then only frames that arrived before the
        line's trigger are recognised as late.
    """

    default_timeout = 2.0
    url_scheme = "aravis://"

    def __init__(self, device_id: str, *, timeout: float | None = None, retries: int = 3,
                 wavelengths: np.ndarray | None = None, dark_prompt: Callable[[str], None] | None = None,
                 shutter_feature: str = "Shutter", shutter_values: tuple[str, str] = ("Open", "Closed"),
                 n_buffers: int = 16, name: str | None = None, frame_ids: bool = True):
        self.Aravis, self.GLib = import_aravis()
        self.device_id = str(device_id)
        self._name = name or f"{self.url_scheme}{self.device_id}"
        self.timeout = float(self.default_timeout if timeout is None else timeout)
        self.retries = int(retries)
        self._calibration = None if wavelengths is None else np.asarray(wavelengths, np.float64)
        self.dark_prompt = dark_prompt
        self.shutter_feature, self.shutter_values = shutter_feature, tuple(shutter_values)
        self.n_buffers = int(n_buffers)
        self.events: list[str] = []
        self.lost_buffers = 0
        self._ledger = TriggerLedger(self._name, frame_ids=frame_ids)
        self._control_lost = False
        self._acquiring: str | None = None   # None, "trigger" or "free"
        self._shutter_open: bool | None = None
        self._t_ms: float | None = None
        self._stream = None
        try:
            self.cam = self.Aravis.Camera.new(self.device_id)
        except Exception as exc:  # GLib.Error: no such device / not reachable
            raise DeviceError(f"cannot open GenICam camera {self.device_id!r} ({gerror(exc)}); "
                              "'mehs capture --list-cameras' lists the cameras Aravis finds",
                              self._name) from None
        self.dev = self.cam.get_device()
        # The handler holds this object weakly: with a bound method the device kept the
        # camera and the camera the device, so a refused or unclosed camera kept its
        # device and heartbeat thread for good, or left them to whichever thread let go
        # last — finalised on its own heartbeat thread (where this handler runs) a
        # device joins that thread from itself and GLib aborts the process ("Resource
        # deadlock avoided"). See close() and __del__.
        self._lost_handler = self.dev.connect("control-lost", _control_lost(weakref.ref(self)))
        try:
            self._configure()
        except BaseException:
            self.close()        # release the device here, not at the collector's whim
            raise

    # ------------------------------------------------------------ plumbing
    @classmethod
    def open(cls, url: str, *, timeout: float | None = None, **kwargs: Any) -> "GenicamCamera":
        """Open ``aravis://DEVICE-ID`` or ``genicam://DEVICE-ID`` (option ``?frame-ids=off``)."""
        for s in SCHEMES:
            if str(url).startswith(s):
                dev, _, query = str(url)[len(s):].partition("?")
                if not dev:
                    raise InputError(f"camera URL {url!r} names no device; give {s}DEVICE-ID")
                if query:
                    if query not in ("frame-ids=off", "frame-ids=on"):
                        raise InputError(f"camera URL {url!r}: unknown option {query!r} "
                                         "(the one option is ?frame-ids=off)")
                    kwargs["frame_ids"] = query == "frame-ids=on"
                return cls(dev, timeout=timeout, name=str(url), **kwargs)
        raise InputError(f"not a GenICam camera URL: {url!r} (use aravis://DEVICE-ID)")

    @property
    def name(self) -> str:
        return self._name

    def _configure(self) -> None:
        entries = self.dev.dup_available_enumeration_feature_values_as_strings
        fmts = list(self._gi("PixelFormat entries", lambda: entries("PixelFormat")) or [])
        current = self._str("PixelFormat")
        usable = [f for f in pixfmt.PREFERRED if f in fmts]
        if current in pixfmt.PREFERRED:
            chosen = current
        elif usable:
            chosen = usable[0]
            self._set_str("PixelFormat", chosen)
        else:
            raise DeviceError(f"camera offers pixel formats {fmts or [current]}; mehs needs one of "
                              f"{', '.join(pixfmt.PREFERRED)} (≥ 10-bit monochrome spectral frames)",
                              self.name)
        self.pixel_format = chosen
        self.pixel_code = pixfmt.PIXEL_FORMATS[chosen]
        self.width, self.height = self._int("Width"), self._int("Height")
        if self._has("AcquisitionMode"):
            self._set_str("AcquisitionMode", "Continuous")
        for auto in ("ExposureAuto", "GainAuto"):
            # a bracket needs the integration times it asks for, and a fixed gain
            if self._has(auto):
                self._set_str(auto, "Off")
        self.payload = self._int("PayloadSize") if self._has("PayloadSize") else \
            pixfmt.frame_bytes(self.pixel_code, self.width, self.height)
        self._stream = self._gi("creating the stream", lambda: self.cam.create_stream(None, None))
        if self._stream is None:
            raise DeviceError("Aravis could not create a stream (is another program streaming "
                              "from this camera?)", self.name)
        for _ in range(self.n_buffers):
            self._stream.push_buffer(self.Aravis.Buffer.new_allocate(self.payload))

    # ------------------------------------------------------------ LineCamera interface
    def identify(self) -> str:
        parts = [self._safe_str(f) for f in ("DeviceVendorName", "DeviceModelName",
                                              "DeviceSerialNumber", "DeviceVersion")]
        if not parts[2]:
            parts[2] = self._safe_str("DeviceID")
        return ",".join(parts)

    def _safe_str(self, f: str) -> str:
        try:
            return self._str(f).strip() if self._has(f) else ""
        except DeviceError:
            return ""

    def shape(self) -> tuple[int, int]:
        """``(samples, bands)`` = ``(Width, Height)`` of a spectral frame."""
        self.width, self.height = self._int("Width"), self._int("Height")
        return self.width, self.height

    def binning(self) -> int:
        """Spectral (vertical) binning factor, 1 when the camera has none."""
        return self._int("BinningVertical") if self._has("BinningVertical") else 1

    def wavelengths(self) -> np.ndarray:
        """Band centres (nm): the calibration given, else the camera's polynomial features."""
        bands = self.shape()[1]
        if self._calibration is not None:
            if self._calibration.size != bands:
                raise InputError(f"the wavelength calibration has {self._calibration.size} values but "
                                 f"the camera sends {bands} bands (binning {self.binning()})")
            return self._calibration.copy()
        names = ("WavelengthCoefficientA", "WavelengthCoefficientB", "WavelengthCoefficientC")
        if not all(self._has(f) for f in names):
            raise DeviceError("the camera has no wavelength calibration features "
                              f"({', '.join(names)}); give the vendor calibration with --wavelengths FILE",
                              self.name)
        # SFNC: binning shrinks the image first, then OffsetY picks the region inside the
        # binned image; the polynomial is in full-resolution sensor rows
        binning = self.binning()
        off = (self._int("OffsetY") if self._has("OffsetY") else 0) * binning
        wl = polynomial_wavelengths([self._float(f) for f in names], bands, binning, off)
        return np.round(wl, 3)

    def fwhm(self) -> np.ndarray:
        raise DeviceError("GenICam cameras do not report band widths", self.name)

    def bit_depth(self) -> int:
        bits = pixfmt.SIGNIFICANT_BITS[self.pixel_format]
        if self._has("PixelDynamicRangeMax"):
            bits = min(bits, int(self._int("PixelDynamicRangeMax")).bit_length())
        return bits

    def set_integration_time(self, ms: float) -> float:
        """Set ``ExposureTime`` (or ``ExposureTimeAbs``); returns the time the camera uses (ms)."""
        self._set_num(self._feature(EXPOSURE_TIME, "exposure time"), float(ms) * 1000.0)
        self._t_ms = self.integration_time()
        return self._t_ms

    def integration_time(self) -> float:
        return round(self._num(self._feature(EXPOSURE_TIME, "exposure time")) / 1000.0, 6)

    def has_shutter(self) -> bool:
        return self._has(self.shutter_feature)

    def set_shutter(self, open_: bool) -> None:
        """Open/close the shutter feature, or ask a person (``dark_prompt``) to (un)cap the lens."""
        open_ = bool(open_)
        if self.has_shutter():
            self._set_str(self.shutter_feature, self.shutter_values[0 if open_ else 1])
        elif self._shutter_open != open_ or self._shutter_open is None:
            if self.dark_prompt is None:
                if open_:
                    self._shutter_open = True
                    return
                raise DeviceError(f"the camera has no {self.shutter_feature!r} feature, so it cannot take "
                                  "dark references by itself: use --dark-prompt (cap the lens when asked)",
                                  self.name)
            self.dark_prompt("open" if open_ else "close")
        self._shutter_open = open_

    def temperature(self) -> float | None:
        return self._float("DeviceTemperature") if self._has("DeviceTemperature") else None

    def frame_rate(self) -> float:
        return self._num(self._feature(FRAME_RATE, "frame rate"))

    def set_frame_rate(self, hz: float) -> float:
        """Set ``AcquisitionFrameRate`` (or ``…Abs``, enabling it where SFNC says so); the rate used."""
        if self._has("AcquisitionFrameRateEnable"):   # SFNC: the rate applies only when enabled
            self._gi("AcquisitionFrameRateEnable",
                     lambda: self.dev.set_boolean_feature_value("AcquisitionFrameRateEnable", True))
        self._set_num(self._feature(FRAME_RATE, "frame rate"), float(hz))
        return self.frame_rate()

    def max_frame_rate(self) -> float:
        return self._num_bounds(self._feature(FRAME_RATE, "frame rate"))[1]

    # ------------------------------------------------------------ acquisition
    def _stop(self, flush_s: float | None = None) -> None:
        """AcquisitionStop; after free-running, discard the frames still on the way.

        ``flush_s``: quiet time that ends the flush (default: :attr:`timeout`, the longest a
        frame may be late; 0: no wait, as on close).
        """
        if self._acquiring is not None:
            was, self._acquiring = self._acquiring, None
            if not self._control_lost:
                try:
                    self._gi("AcquisitionStop", lambda: self.dev.execute_command("AcquisitionStop"))
                    if self._has("TLParamsLocked"):
                        self._gi("TLParamsLocked",
                                 lambda: self.dev.set_integer_feature_value("TLParamsLocked", 0))
                except DeviceError:
                    pass
            if was == "free" and not self._control_lost:
                self._flush(self.timeout if flush_s is None else flush_s)
            else:
                self._drain()

    def _flush(self, quiet_s: float) -> None:
        """Receive and discard frames until none came for ``quiet_s`` (bounded by :attr:`timeout`).

        A free-running camera has frames on the way when AcquisitionStop is sent (SFNC: the
        acquisition ends after the current frame; the link adds its latency). Arriving after
        the next acquisition's first trigger, such a frame would be taken for that line, and
        neither its arrival time nor its block id (a camera may number afresh from
        AcquisitionStart) tells it apart: so they are awaited and dropped here, as GenTL
        consumers flush the stream's queue after stopping.
        """
        if self._stream is None:
            return
        quiet_us = int(1e6 * max(0.0, min(float(quiet_s), self.timeout)))
        deadline = time.monotonic() + self.timeout + 2 * (self._t_ms or 0.0) / 1000.0 + 1.0
        n = 0
        while time.monotonic() < deadline:   # (a camera that never stops: give up, leave it to the ledger)
            try:
                b = self._stream.timeout_pop_buffer(quiet_us) if quiet_us else self._stream.try_pop_buffer()
            except Exception:   # GLib error of a vanished camera: nothing more will come
                return
            if b is None:
                break
            n += 1
            self._stream.push_buffer(b)
        if n:
            self.events.append(f"camera: discarded {n} free-running frame(s) still on the way "
                               "after AcquisitionStop")

    def _start(self, mode: str) -> None:
        if self._acquiring == mode:
            return
        self._stop()
        if self._has("TriggerSelector"):
            self._set_str("TriggerSelector", "FrameStart")
        if mode == "trigger":
            self._check_trigger_features()
            self._set_str("TriggerMode", "On")
            self._set_str("TriggerSource", "Software")
        else:
            self._set_str("TriggerMode", "Off")
        if self._has("TLParamsLocked"):
            # what a GenTL producer does: geometry and pixel format stay fixed while streaming
            self._gi("TLParamsLocked", lambda: self.dev.set_integer_feature_value("TLParamsLocked", 1))
        self._gi("AcquisitionStart", lambda: self.dev.execute_command("AcquisitionStart"))
        self._acquiring = mode
        self._ledger.reset()   # a camera may number its frames afresh from AcquisitionStart

    def _drain(self, ledger: TriggerLedger | None = None) -> None:
        """Re-queue every buffer received; with ``ledger`` note and log them (frames of earlier
        triggers). A failed buffer is counted and logged as :meth:`_pop` does: re-queued
        silently, a lost frame went missing from the capture's figures."""
        if self._stream is None:
            return
        while True:
            b = self._stream.try_pop_buffer()
            if b is None:
                return
            try:
                status = b.get_status()
                if status != self.Aravis.BufferStatus.SUCCESS:
                    self.lost_buffers += 1
                    self.events.append(f"camera: buffer {b.get_frame_id()} {status.value_nick} "
                                       "(lost / incomplete)")
                elif ledger is not None:
                    fid = int(b.get_frame_id())
                    ledger.seen(fid)
                    self.events.append(f"camera: dropped frame {fid} of an earlier trigger "
                                       "(arrived before the line's trigger)")
            finally:
                self._stream.push_buffer(b)

    def _frame_wait_us(self) -> int:
        t = (self._t_ms or 0.0) / 1000.0
        return int(1e6 * (self.timeout + 2 * t))

    def _decode(self, buf) -> np.ndarray:
        """Check a SUCCESS buffer against the configured frame and unpack it → ``(samples, bands)``."""
        code = int(buf.get_image_pixel_format())
        w, h = int(buf.get_image_width()), int(buf.get_image_height())
        data = buf.get_image_data()
        if code != self.pixel_code:
            raise DeviceError(f"camera sent {pixfmt.name_of(code)} frames, expected {self.pixel_format}: "
                              "another program changed PixelFormat? Restart the capture with --resume",
                              self.name)
        if (w, h) != (self.width, self.height):
            raise DeviceError(f"camera sent a {w}×{h} frame, expected {self.width}×{self.height} "
                              "(binning or region changed during the capture)", self.name)
        need = pixfmt.frame_bytes(code, w, h)
        if len(data) != need:
            raise DeviceError(f"frame buffer holds {len(data)} bytes, a {w}×{h} {self.pixel_format} frame "
                              f"needs {need} (binned or padded frames are not supported)", self.name)
        return np.ascontiguousarray(pixfmt.unpack(data, code, w, h).T)

    def _pop(self, timeout_us: int):
        """Next buffer; ``None`` on timeout, ``False`` for a failed buffer (counted and re-queued)."""
        if timeout_us > 0:
            b = self._gi("waiting for a frame", lambda: self._stream.timeout_pop_buffer(timeout_us))
        else:
            b = self._gi("polling frames", lambda: self._stream.try_pop_buffer())
        if b is None:
            if self._control_lost:
                raise DeviceDisconnected("camera control channel lost (unplugged?)", self.name)
            return None
        status = b.get_status()
        if status != self.Aravis.BufferStatus.SUCCESS:
            self.lost_buffers += 1
            self.events.append(f"camera: buffer {b.get_frame_id()} {status.value_nick} (lost / incomplete)")
            self._stream.push_buffer(b)
            return False
        return b

    def read_line(self) -> np.ndarray:
        """Software-trigger one frame and return it: uint16 ``(samples, bands)``.

        A timeout or an incomplete buffer triggers the line again (the stage has
        not moved), up to ``retries`` times. A frame of an earlier line's trigger
        (late: it came after the stage moved on) is dropped and logged, and the
        wait for this line's frame goes on.
        """
        self._start("trigger")
        led = self._ledger
        self._drain(led)  # frames of an earlier, abandoned trigger that already arrived
        led.begin_line(time.time_ns())
        last = "no frame"
        for attempt in range(self.retries + 1):
            led.triggered()
            self._gi("TriggerSoftware", lambda: self.dev.execute_command("TriggerSoftware"))
            deadline = time.monotonic() + self._frame_wait_us() / 1e6
            while True:
                left_us = int((deadline - time.monotonic()) * 1e6)
                b = self._pop(left_us) if left_us > 0 else None
                if b is None:
                    last = f"no frame within {self._frame_wait_us() / 1e6:.1f} s"
                    self.events.append("camera: timeout waiting for a triggered frame "
                                       f"(attempt {attempt + 1})")
                    if led.timed_out():
                        self.events.append("camera: frame count re-synchronised after a timeout "
                                           "(the camera ignored a trigger?)")
                    break
                if b is False:
                    last = "incomplete frame (lost packets)"
                    break
                try:
                    fid = int(b.get_frame_id())
                    why = led.stale_reason(fid, int(b.get_system_timestamp()))
                    if why is None:
                        return self._decode(b)
                    self.events.append(f"camera: dropped late frame {fid} of an earlier trigger ({why})")
                finally:
                    self._stream.push_buffer(b)
        err = DeviceDisconnected if self._control_lost else DeviceTimeout
        raise err(f"{last} (after {self.retries + 1} triggers of one line)", self.name)

    def stream(self, frame_rate_hz: float) -> "FrameStream":
        """Free-run at ``frame_rate_hz`` (constant-velocity scans); use as a context manager."""
        return FrameStream(self, frame_rate_hz)

    def close(self) -> None:
        try:
            self._stop(flush_s=0.0)
        except DeviceError:
            pass
        if self.dev is not None and getattr(self, "_lost_handler", None) is not None:
            self.dev.disconnect(self._lost_handler)
            self._lost_handler = None
            # a "control-lost" emission already under way holds its own reference to the
            # device while its handler waits for the GIL: let it run (it sets the flag)
            time.sleep(0)
        held = [self._stream, self.dev, self.cam]
        self._stream = None
        self.cam = self.dev = None
        if self._control_lost:
            # Releasing a vanished device waits out GVCP timeouts (~10 s): the last
            # references go on the release thread so the error reaches the user at
            # once (after a pause that lets an emission in flight drop its reference
            # first: the last one must not go on the heartbeat thread)
            _release_elsewhere(held, delay_s=0.2)
        else:
            held.clear()

    def __del__(self) -> None:
        # Not closed: the Aravis objects go on the release thread, never on whatever
        # thread dropped the last reference or ran the cycle collector (the device's
        # heartbeat thread finalising it would join itself; the simulated camera's own
        # thread would wait on its own replies).
        held = [getattr(self, n, None) for n in ("_stream", "dev", "cam")]
        if any(h is not None for h in held):
            self._stream = self.dev = self.cam = None
            _release_elsewhere(held)

    def __enter__(self):
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()
