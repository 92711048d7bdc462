"""A GenICam camera's Aravis objects are released where no thread waits on itself (Aravis 0.8).

A fresh-clone CI run died in the GigE Vision tests with GLib's abort
(``g_system_thread_wait``: "Resource deadlock avoided", SIGTRAP), and a loop of those tests
did once in two runs: an Aravis device finalised on its own heartbeat thread joins that
thread from itself. ``GenicamCamera`` listened for the device's "control-lost" signal —
emitted on the heartbeat thread, holding a reference to the device while its Python
handler waits for the GIL — with a bound method: the device held the camera object, which
held the device. A camera refused while opening (no 12-bit pixel format) kept its device,
heartbeat and all, to the end of the process; one dropped without ``close()`` left it to
whichever thread dropped it or ran the cycle collector. Now the handler holds the camera
weakly, ``close()`` disconnects it and lets an emission under way finish before a lost
device is dropped, a refused camera closes itself, and a camera dropped unclosed hands its
Aravis objects to one release thread.
"""

import gc
import weakref

import pytest

from mehs.capture.aravis import aravis_available

_why = aravis_available()
pytestmark = [pytest.mark.skipif(_why is not None, reason=f"Aravis unavailable: {_why}"),
              pytest.mark.usefixtures("gvcp_port_turns")]

from mehs.capture.scene import make_scene  # noqa: E402
from mehs.capture.sensor import SensorModel  # noqa: E402
from mehs.errors import DeviceError  # noqa: E402


def _sim(**kw):
    from mehs.capture.genicam_sim import SimGenicamDevices

    scene = make_scene("colorchecker", lines=8, samples=8, seed=1)
    return SimGenicamDevices(scene, SensorModel(seed=1), **kw)


def _freed_without_the_collector(drop) -> bool:
    """Whether the object ``drop()`` lets go of is freed by its last reference alone."""
    gc.collect()
    gc.disable()
    try:
        ref = drop()
        return ref() is None
    finally:
        gc.enable()


def test_a_refused_camera_releases_its_device_at_once(monkeypatch):
    from mehs.capture.genicam import GenicamCamera

    made = []
    real = GenicamCamera._configure

    def configure(self):
        made.append(weakref.ref(self))
        real(self)

    monkeypatch.setattr(GenicamCamera, "_configure", configure)
    with _sim(pixel_format="Mono8", pixel_formats=("Mono8",)) as dev:
        def drop():
            with pytest.raises(DeviceError, match="offers pixel formats") as info:
                GenicamCamera.open(dev.camera_url)
            del info                                   # (its traceback holds the camera)
            return made[0]

        assert _freed_without_the_collector(drop)


def test_a_camera_dropped_without_close_is_freed_by_its_last_reference():
    from mehs.capture.genicam import GenicamCamera

    with _sim() as dev:
        def drop():
            cam = GenicamCamera.open(dev.camera_url)
            ref = weakref.ref(cam)
            del cam
            return ref

        assert _freed_without_the_collector(drop)


def test_control_lost_still_reaches_the_camera():
    """The signal handler holds the camera weakly, and still marks it — emitted, as Aravis
    does, from another thread than the one that holds the camera."""
    import threading

    from mehs.capture.genicam import GenicamCamera

    with _sim() as dev:
        cam = GenicamCamera.open(dev.camera_url)
        try:
            assert not cam._control_lost
            heartbeat = threading.Thread(target=cam.dev.emit, args=("control-lost",),
                                         name="heartbeat")
            heartbeat.start()
            heartbeat.join(10)
            assert not heartbeat.is_alive()
            assert cam._control_lost
        finally:
            cam.close()


def test_the_device_of_a_camera_dropped_without_close_goes_on_the_release_thread():
    """Not on the thread that dropped it (nor the collector's): the release thread
    finalises it, which stops its heartbeat thread and leaves control."""
    import threading
    import time

    from mehs.capture.genicam import GenicamCamera

    with _sim() as dev:
        cam = GenicamCamera.open(dev.camera_url)
        where = []
        keep = cam.dev.weak_ref(lambda: where.append(threading.current_thread().name))
        del cam
        deadline = time.monotonic() + 30
        while not where and time.monotonic() < deadline:
            time.sleep(0.05)
        del keep
    assert where == ["mehs-genicam-release"]


def test_a_closed_camera_releases_its_device_before_close_returns():
    import threading

    from mehs.capture.genicam import GenicamCamera

    with _sim() as dev:
        cam = GenicamCamera.open(dev.camera_url)
        where = []
        keep = cam.dev.weak_ref(lambda: where.append(threading.current_thread().name))
        cam.close()
        assert where == [threading.current_thread().name]       # here, and done
        del keep


def test_a_camera_that_fails_while_starting_stops_serving_at_once(monkeypatch):
    """A failure after the fake camera came up disposes it there and then — not when the
    failure's traceback (whose frame still names it) goes — so the next simulator can serve
    the GigE Vision port while the caller still holds the error."""
    from mehs.capture.genicam_sim import GenicamSimCamera

    def broken(*args):
        raise RuntimeError("register write failed")

    dev = _sim()
    monkeypatch.setattr(GenicamSimCamera, "_write_double", staticmethod(broken))
    try:
        with pytest.raises(RuntimeError, match="register write failed") as failed:
            dev.start()
    finally:
        dev.close()
    monkeypatch.undo()
    assert failed.tb is not None          # the traceback, with its frames, is still held
    with _sim() as again:
        assert again.camera._gv is not None and again.camera._gv.is_running()


def test_a_stage_server_that_cannot_start_closes_the_camera(monkeypatch):
    """``start()`` used as a context manager has no ``__exit__`` when it raises: the camera
    it started must not keep the port (this process's next simulator would be refused)."""
    dev = _sim()

    def broken():
        raise OSError("cannot start the stage's thread")

    monkeypatch.setattr(dev.server, "start", broken)
    with pytest.raises(OSError, match="stage's thread"):
        with dev:
            pass
    assert dev.camera._gv is None
    with _sim() as again:
        assert again.camera._gv.is_running()
