"""A GenICam camera's device is released on the thread that lets it go (Aravis 0.8).

``GenicamCamera`` listened for the device's "control-lost" signal with a bound method: the
device held the camera object, the camera the device, a reference cycle. A camera refused
while opening (no 12-bit pixel format) or dropped without ``close()`` then lived until
Python's cycle collector ran — on whatever thread allocated at that moment, among them
the device's own heartbeat thread, which calls into Python when it signals "control-lost"
after the camera's simulator stopped. Finalising the device there joins the heartbeat
thread from itself: GLib aborts the process (``g_system_thread_wait``: "Resource deadlock
avoided", SIGTRAP), seen once in about 20 runs of the GigE Vision tests.
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
    """The signal handler holds the camera weakly, and still marks it."""
    from mehs.capture.genicam import GenicamCamera

    with _sim() as dev:
        cam = GenicamCamera.open(dev.camera_url)
        try:
            cam.dev.emit("control-lost")
            assert cam._control_lost
        finally:
            cam.close()
