"""mehs's GenICam driver against an independent GigE Vision camera: Aravis's stock fake camera.

Every other GigE Vision test runs against mehs's own simulator (its XML, its fill pattern). Here
the camera is ``arv-fake-gv-camera-0.8`` (aravis-tools) with Aravis's own ``arv-fake-camera.xml``:
an area camera (512×512, Mono8 default, Mono16), SFNC 1.x spellings (``ExposureTimeAbs``), no
shutter, no spectral calibration. Truth for the pixels is Aravis's fill pattern
(``arvfakecamera.c``, ``arv_fake_camera_diagonal_ramp``, Mono16 case): pixel (x, y) of frame
``id`` = clamp(((256·(x + id + y)) mod 65535) · scale), scale = 1 + gain + log10(t_µs / 10000),
written as a native (x86: little-endian) uint16 — the PFNC Mono16 byte order.

GVCP has one port per host (3956): the process holds the mehs simulators' cross-process lock
(:class:`~mehs.capture.gvcp_lock.GvcpPortLock`, waiting ``MEHS_GVCP_WAIT_S``) while the stock
camera serves, so it takes turns with the simulator tests. Skips when aravis-tools is absent.
"""

import shutil
import subprocess
import time

import numpy as np
import pytest

from mehs.capture.aravis import aravis_available
from mehs.errors import DeviceError

STOCK = "arv-fake-gv-camera-0.8"
_why = aravis_available()
pytestmark = [pytest.mark.skipif(_why is not None, reason=f"Aravis unavailable: {_why}"),
              pytest.mark.skipif(shutil.which(STOCK) is None, reason=f"{STOCK} not installed (aravis-tools)")]

SERIAL = "MEHSH22STOCK"


@pytest.fixture(scope="module")
def stock_camera():
    """``arv-fake-gv-camera-0.8 -i 127.0.0.1`` serving, under the GVCP port lock; yields its URL."""
    from mehs.capture.gvcp_lock import GvcpPortLock

    mp = pytest.MonkeyPatch()
    mp.setenv("MEHS_GVCP_WAIT_S", "900")      # another run's simulator: wait for it (as conftest)
    lock = GvcpPortLock("127.0.0.1").acquire()
    proc = subprocess.Popen([STOCK, "-i", "127.0.0.1", "-s", SERIAL],
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    try:
        from mehs.capture.aravis import import_aravis

        Aravis, _ = import_aravis()
        deadline = time.monotonic() + 60   # (a moment when idle: 0.03 s; 0.2 s on a busy host)
        while True:            # wait until it answers GVCP (a fresh process needs a moment)
            try:
                Aravis.Camera.new("127.0.0.1")
                break
            except Exception:
                if proc.poll() is not None or time.monotonic() > deadline:
                    pytest.fail(f"{STOCK} did not start: {proc.stderr.read().decode()[-2000:]}")
                time.sleep(0.1)
        yield "aravis://127.0.0.1"
    finally:
        proc.terminate()
        try:
            proc.wait(timeout=5)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
        lock.release()
        mp.undo()


def _ramp(width, height, frame_id, exposure_us, gain=0):
    """Aravis's Mono16 diagonal ramp (truth), as mehs returns a frame: (samples=x, bands=y)."""
    x = np.arange(width, dtype=np.int64)[:, None]
    y = np.arange(height, dtype=np.int64)[None, :]
    scale = 1.0 + gain + np.log10(exposure_us / 10000.0)
    v = ((256 * (x + frame_id + y)) % 65535).astype(np.float64) * scale
    return np.clip(v, 0, 65535).astype(np.uint16)


def _frame_id_of(line, exposure_us):
    """The frame id whose ramp this frame is (the fake camera's internal counter), or None."""
    ids = np.arange(65536, dtype=np.int64)      # the ramp repeats after 65535 ids
    scale = 1.0 + np.log10(exposure_us / 10000.0)
    v00 = np.clip(((256 * ids) % 65535).astype(np.float64) * scale, 0, 65535).astype(np.uint16)
    for fid in np.nonzero(v00 == line[0, 0])[0]:   # pixel (0, 0) narrows it to one or two ids
        if np.array_equal(_ramp(line.shape[0], line.shape[1], int(fid), exposure_us), line):
            return int(fid)
    return None


def test_discovery_and_open_pick_mono16(stock_camera):
    from mehs.capture.aravis import list_cameras
    from mehs.capture.genicam import GenicamCamera

    ids = [c for c in list_cameras() if c["serial"] == SERIAL]
    assert ids and ids[0]["vendor"] == "Aravis" and ids[0]["address"] == "127.0.0.1", ids
    with GenicamCamera.open(stock_camera, timeout=1.0) as cam:
        assert cam.identify().split(",")[:3] == ["Aravis", "Fake", SERIAL]
        assert cam.pixel_format == "Mono16"     # the camera starts in Mono8: mehs switches
        assert cam.shape() == (512, 512)
        assert cam.bit_depth() == 16
        assert cam.temperature() is None
        assert cam.max_frame_rate() == pytest.approx(1000.0)


def test_exposure_time_abs_set_and_read_back(stock_camera):
    """The stock XML has SFNC 1.x ``ExposureTimeAbs`` (µs), no ``ExposureTime``: before, every
    exposure failed with Aravis's bare "[ExposureTime] Not found"."""
    from mehs.capture.genicam import GenicamCamera

    with GenicamCamera.open(stock_camera, timeout=1.0) as cam:
        assert cam.set_integration_time(2.5) == pytest.approx(2.5)
        assert cam.integration_time() == pytest.approx(2.5)
        assert cam.dev.get_float_feature_value("ExposureTimeAbs") == pytest.approx(2500.0)
        assert cam.set_integration_time(10.0) == pytest.approx(10.0)


def test_triggered_frame_equals_aravis_ramp(stock_camera):
    """A software-triggered Mono16 frame, decoded by mehs, equals the fake camera's own pattern:
    pixel values, orientation (Width = samples, Height = bands) and byte order (little-endian)."""
    from mehs.capture.genicam import GenicamCamera

    with GenicamCamera.open(stock_camera, timeout=1.0) as cam:
        for t_ms in (10.0, 20.0):
            cam.set_integration_time(t_ms)
            line = cam.read_line()
            assert line.shape == (512, 512) and line.dtype == np.uint16
            fid = _frame_id_of(line, t_ms * 1000.0)
            assert fid is not None, f"{t_ms} ms: frame is not Aravis's Mono16 ramp"
            swapped = line.byteswap()
            assert _frame_id_of(swapped, t_ms * 1000.0) is None   # the test tells byte orders apart
        assert not [e for e in cam.events if "timeout" in e], cam.events


def test_free_running_stream_and_back_to_triggered(stock_camera):
    from mehs.capture.genicam import GenicamCamera

    with GenicamCamera.open(stock_camera, timeout=1.0) as cam:
        cam.set_integration_time(10.0)
        t0 = time.time()
        with cam.stream(20.0) as s:
            got = []
            deadline = time.monotonic() + 30.0    # 3 frames at 20 Hz: a bound, not a window
            while len(got) < 3 and time.monotonic() < deadline:
                got += s.poll(0.5)
            frames = s.frames()
        t1 = time.time()
        assert s.rate == pytest.approx(20.0)
        assert cam.frame_rate() == pytest.approx(20.0)
        assert len(frames) >= 3
        for f in frames:
            # host mid-exposure times inside the acquisition (the fake camera stamps host time)
            assert t0 - 0.5 < f.t < t1 + 0.5, (t0, f.t, t1)
            assert _frame_id_of(f.line, 10000.0) is not None
        assert np.all(np.diff([f.t for f in frames]) > 0)
        assert cam.read_line().shape == (512, 512)   # step mode after free-running


def test_missing_line_scan_features_are_named(stock_camera):
    """What a line-scan HS camera has and the stock camera lacks is a clear error, not a crash."""
    from mehs.capture.genicam import GenicamCamera

    with GenicamCamera.open(stock_camera, timeout=1.0) as cam:
        with pytest.raises(DeviceError, match=r"no wavelength calibration features.*--wavelengths FILE"):
            cam.wavelengths()
        with pytest.raises(DeviceError, match=r"no 'Shutter' feature.*--dark-prompt"):
            cam.set_shutter(False)
        with pytest.raises(DeviceError, match="do not report band widths"):
            cam.fwhm()
    with GenicamCamera.open(stock_camera, timeout=1.0, wavelengths=np.linspace(400, 1000, 512)) as cam:
        assert cam.wavelengths().shape == (512,)
