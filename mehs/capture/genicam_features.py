"""GenICam feature access for :class:`~mehs.capture.genicam.GenicamCamera`: errors, and SFNC spellings.

Real cameras spell some features the way an older SFNC did, or a vendor does: a
Basler ace GigE, an Allied Vision Manta/Mako, Aravis's own stock fake camera
(``arv-fake-gv-camera-0.8``) have ``ExposureTimeAbs`` and ``AcquisitionFrameRateAbs``
(SFNC 1.x) where SFNC 2 says ``ExposureTime`` / ``AcquisitionFrameRate``; XIMEA
cameras make ``ExposureTime`` an Integer. Both carry the same quantity in the same
unit (µs, Hz), so the driver takes the first spelling a camera has
(:data:`EXPOSURE_TIME`, :data:`FRAME_RATE`) and reads / writes it as the node's type,
and a camera with none is a :class:`~mehs.errors.DeviceError` naming every spelling
looked for (not Aravis's bare ``[ExposureTime] Not found``).

References
----------
EMVA, *GenICam SFNC 2.7*, 2022, §"Acquisition Control" (ExposureTime, AcquisitionFrameRate;
the ``…Abs`` / ``…Raw`` variants are deprecated names of SFNC 1.x). Aravis 0.8.26,
``src/arvcamera.c`` (``arv_camera_set_exposure_time``: ``ExposureTime`` else
``ExposureTimeAbs``, Integer ``ExposureTime`` for XIMEA; ``arv_camera_set_frame_rate``:
``AcquisitionFrameRate`` else ``AcquisitionFrameRateAbs``); ``src/arv-fake-camera.xml``.
"""

from __future__ import annotations

from typing import Any, Callable

from mehs.errors import DeviceDisconnected, DeviceError

#: Integration time (µs), SFNC 2 spelling first.
EXPOSURE_TIME = ("ExposureTime", "ExposureTimeAbs")
#: Free-running frame rate (Hz), SFNC 2 spelling first.
FRAME_RATE = ("AcquisitionFrameRate", "AcquisitionFrameRateAbs")
#: What a step-mode (software-triggered) line needs.
TRIGGER_FEATURES = ("TriggerMode", "TriggerSource", "TriggerSoftware")


def gerror(exc: BaseException) -> str:
    return getattr(exc, "message", None) or str(exc)


class FeatureAccess:
    """Mixin: typed feature reads/writes through ``self.dev`` with errors that name the camera.

    Needs ``self.dev`` (ArvDevice), ``self.Aravis``, ``self.GLib``, ``self.name`` and
    ``self._control_lost``.
    """

    _aliases: dict[tuple[str, ...], str]

    def _gi(self, what: str, fn: Callable[[], Any]) -> Any:
        """Run an Aravis call; GLib errors become DeviceError / DeviceDisconnected."""
        if self._control_lost:
            raise DeviceDisconnected(f"camera control channel lost (unplugged?) before {what}", self.name)
        try:
            return fn()
        except Exception as exc:
            if not isinstance(exc, self.GLib.Error):
                raise
            if self._control_lost or "timeout" in gerror(exc).lower():
                self._control_lost = True
                raise DeviceDisconnected(f"camera stopped answering on {what} ({gerror(exc)}): "
                                         "unplugged or powered off?", self.name) from None
            raise DeviceError(f"{what}: {gerror(exc)}", self.name) from None

    def _has(self, feature: str) -> bool:
        return bool(self._gi(f"feature {feature}", lambda: self.dev.is_feature_available(feature)))

    def _int(self, f: str) -> int:
        return int(self._gi(f"reading {f}", lambda: self.dev.get_integer_feature_value(f)))

    def _float(self, f: str) -> float:
        return float(self._gi(f"reading {f}", lambda: self.dev.get_float_feature_value(f)))

    def _str(self, f: str) -> str:
        return str(self._gi(f"reading {f}", lambda: self.dev.get_string_feature_value(f)))

    def _set_str(self, f: str, v: str) -> None:
        self._gi(f"setting {f}={v}", lambda: self.dev.set_string_feature_value(f, v))

    # ------------------------------------------------------------ spellings and node types
    def _feature(self, names: tuple[str, ...], need: str) -> str:
        """The first of ``names`` the camera has (cached); DeviceError naming them all when none."""
        if not hasattr(self, "_aliases"):
            self._aliases = {}
        hit = self._aliases.get(names)
        if hit is None:
            hit = next((f for f in names if self._has(f)), None)
            if hit is None:
                raise DeviceError(f"the camera has no {need} feature (looked for {' / '.join(names)}); "
                                  "mehs cannot drive it", self.name)
            self._aliases[names] = hit
        return hit

    def _is_int(self, f: str) -> bool:
        node = self._gi(f"feature {f}", lambda: self.dev.get_feature(f))
        return isinstance(node, self.Aravis.GcInteger) and not isinstance(node, self.Aravis.GcFloat)

    def _num(self, f: str) -> float:
        """A Float or Integer feature's value."""
        return float(self._int(f)) if self._is_int(f) else self._float(f)

    def _set_num(self, f: str, v: float) -> None:
        if self._is_int(f):
            iv = int(round(float(v)))
            self._gi(f"setting {f}={iv}", lambda: self.dev.set_integer_feature_value(f, iv))
        else:
            self._gi(f"setting {f}={v:g}", lambda: self.dev.set_float_feature_value(f, float(v)))

    def _num_bounds(self, f: str) -> tuple[float, float]:
        if self._is_int(f):
            lo, hi = self._gi(f"{f} bounds", lambda: self.dev.get_integer_feature_bounds(f))
        else:
            lo, hi = self._gi(f"{f} bounds", lambda: self.dev.get_float_feature_bounds(f))
        return float(lo), float(hi)

    def _check_trigger_features(self) -> None:
        """Step mode needs software triggers: say which features are missing, and the way out."""
        missing = [f for f in TRIGGER_FEATURES if not self._has(f)]
        if missing:
            raise DeviceError(f"the camera has no {', '.join(missing)} feature(s), so it cannot be "
                              "software-triggered one line at a time (step mode); use --scan continuous "
                              "(free-running) if it can free-run", self.name)
