"""SFNC spellings and node types real cameras use, on a feature table (no Aravis needed).

Truth: Aravis 0.8's ``arvcamera.c`` (what a vendor-neutral GenICam consumer must handle:
``ExposureTime`` else ``ExposureTimeAbs``; XIMEA's Integer ``ExposureTime``;
``AcquisitionFrameRate`` else ``AcquisitionFrameRateAbs``), Aravis's stock
``arv-fake-camera.xml`` (``ExposureTimeAbs`` only), and SFNC 2.7 (units µs and Hz for all
spellings). The stock camera itself is driven in ``test_h22_gige_stock_camera.py``.
"""

import pytest

from mehs.capture.genicam import GenicamCamera
from mehs.errors import DeviceError


class _GcFloat:
    pass


class _GcInteger:
    pass


class _GError(Exception):
    @property
    def message(self):
        return str(self)


class _Node:
    def __init__(self, kind, value, bounds):
        self.kind, self.value, self.bounds = kind, value, bounds


class _FloatNode(_Node, _GcFloat):
    pass


class _IntNode(_Node, _GcInteger):
    pass


class _Dev:
    """An ArvDevice over a feature table; unknown features fail as Aravis's do."""

    def __init__(self, features):
        self.f = features
        self.calls = []

    def _get(self, name):
        if name not in self.f:
            raise _GError(f"[{name}] Not found")
        return self.f[name]

    def is_feature_available(self, name):
        return name in self.f

    def get_feature(self, name):
        return self.f.get(name)

    def get_float_feature_value(self, name):
        n = self._get(name)
        if not isinstance(n, _GcFloat):
            raise _GError(f"[{name}:ArvGcIntegerNode] Not a ArvGcFloat")
        return n.value

    def get_integer_feature_value(self, name):
        n = self._get(name)
        if not isinstance(n, _GcInteger):
            raise _GError(f"[{name}:ArvGcFloatNode] Not a ArvGcInteger")
        return n.value

    def set_float_feature_value(self, name, v):
        self.calls.append(("float", name, v))
        n = self._get(name)
        if not isinstance(n, _GcFloat):
            raise _GError(f"[{name}:ArvGcIntegerNode] Not a ArvGcFloat")
        n.value = float(v)

    def set_integer_feature_value(self, name, v):
        self.calls.append(("int", name, v))
        n = self._get(name)
        if not isinstance(n, _GcInteger):
            raise _GError(f"[{name}:ArvGcFloatNode] Not a ArvGcInteger")
        n.value = int(v)

    def get_float_feature_bounds(self, name):
        return self._get(name).bounds

    def get_integer_feature_bounds(self, name):
        return self._get(name).bounds

    def set_boolean_feature_value(self, name, v):
        self.calls.append(("bool", name, v))

    def set_string_feature_value(self, name, v):
        self.calls.append(("str", name, v))
        self._get(name)

    def execute_command(self, name):
        self.calls.append(("cmd", name))
        self._get(name)


def _camera(features):
    cam = object.__new__(GenicamCamera)
    cam.Aravis = type("Aravis", (), {"GcFloat": _GcFloat, "GcInteger": _GcInteger})
    cam.GLib = type("GLib", (), {"Error": _GError})
    cam.dev = _Dev(features)
    cam._name, cam._control_lost, cam._t_ms = "aravis://table", False, None
    return cam


def test_exposure_time_abs_of_sfnc1_cameras():
    """Basler ace GigE, AVT Manta, Aravis's stock fake camera: ``ExposureTimeAbs`` (µs)."""
    cam = _camera({"ExposureTimeAbs": _FloatNode("f", 10000.0, (10.0, 1e7))})
    assert cam.set_integration_time(2.5) == pytest.approx(2.5)
    assert cam.dev.f["ExposureTimeAbs"].value == pytest.approx(2500.0)
    assert cam.integration_time() == pytest.approx(2.5)


def test_sfnc2_spelling_wins_when_both_exist():
    cam = _camera({"ExposureTime": _FloatNode("f", 1000.0, (1.0, 1e6)),
                   "ExposureTimeAbs": _FloatNode("f", 1000.0, (1.0, 1e6))})
    cam.set_integration_time(4.0)
    assert cam.dev.f["ExposureTime"].value == pytest.approx(4000.0)
    assert cam.dev.f["ExposureTimeAbs"].value == pytest.approx(1000.0)


def test_integer_exposure_time_of_ximea_cameras():
    cam = _camera({"ExposureTime": _IntNode("i", 1000, (1, 1000000))})
    assert cam.set_integration_time(2.0004) == pytest.approx(2.0)     # whole µs: what it uses
    assert ("int", "ExposureTime", 2000) in cam.dev.calls


def test_no_exposure_feature_names_every_spelling():
    cam = _camera({})
    with pytest.raises(DeviceError, match=r"no exposure time feature \(looked for ExposureTime / "
                                          r"ExposureTimeAbs\)"):
        cam.set_integration_time(1.0)


def test_frame_rate_abs_and_enable():
    cam = _camera({"AcquisitionFrameRateAbs": _FloatNode("f", 25.0, (0.1, 200.0)),
                   "AcquisitionFrameRateEnable": object()})
    assert cam.set_frame_rate(50.0) == pytest.approx(50.0)
    assert cam.frame_rate() == pytest.approx(50.0)
    assert cam.max_frame_rate() == pytest.approx(200.0)
    assert ("bool", "AcquisitionFrameRateEnable", True) in cam.dev.calls
    assert cam.dev.calls.index(("bool", "AcquisitionFrameRateEnable", True)) < \
        cam.dev.calls.index(("float", "AcquisitionFrameRateAbs", 50.0))


def test_step_mode_without_software_trigger_is_named():
    cam = _camera({"TriggerMode": object(), "AcquisitionStart": object()})
    cam._acquiring, cam._stream = None, None
    with pytest.raises(DeviceError, match=r"no TriggerSource, TriggerSoftware feature.*--scan continuous"):
        cam._start("trigger")
    assert ("cmd", "AcquisitionStart") not in cam.dev.calls     # refused before streaming
