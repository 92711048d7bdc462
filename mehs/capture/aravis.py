"""Loading Aravis 0.8 through PyGObject, and camera discovery.

pip's ``PyGObject`` is used when importable; otherwise Debian's ``python3-gi``
is loaded — only its ``gi`` package, and only when it was built for the
running CPython — so a virtualenv made from the system Python needs no
compiler. Install steps: ``docs/genicam.md``.

References
----------
E. Pacaud, *Aravis 0.8 API reference*, https://aravisproject.github.io/aravis/;
PyGObject, https://pygobject.gnome.org/.
"""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

from mehs.errors import DeviceError

#: URL schemes of GenICam cameras: ``aravis://DEVICE-ID`` or ``genicam://DEVICE-ID``.
SCHEMES = ("aravis://", "genicam://")

#: Where Debian's ``python3-gi`` lives (used only when no ``gi`` is importable).
_DEBIAN_GI = Path("/usr/lib/python3/dist-packages/gi")

INSTALL_HINT = ("Aravis is not installed: apt-get install gir1.2-aravis-0.8 aravis-tools "
                "libgirepository1.0-dev libcairo2-dev pkg-config, then "
                "pip install 'mehs[aravis]' (see docs/genicam.md)")


class AravisUnavailable(DeviceError):
    """PyGObject or the Aravis 0.8 typelib is missing."""


def is_genicam_url(url: str | None) -> bool:
    return bool(url) and str(url).startswith(SCHEMES)


def _load_debian_gi():
    # Debian's python3-gi is compiled for the system CPython; load only the `gi`
    # package from it (not the whole dist-packages, whose numpy etc. would shadow ours).
    init = _DEBIAN_GI / "__init__.py"
    abi = f"cpython-{sys.version_info.major}{sys.version_info.minor}"
    if not init.exists() or not any(abi in p.name for p in _DEBIAN_GI.glob("_gi*.so")):
        raise ImportError("no Debian python3-gi for this Python")
    spec = importlib.util.spec_from_file_location("gi", init, submodule_search_locations=[str(_DEBIAN_GI)])
    mod = importlib.util.module_from_spec(spec)
    sys.modules["gi"] = mod
    try:
        spec.loader.exec_module(mod)
    except Exception:
        del sys.modules["gi"]
        raise
    return mod


def import_aravis():
    """``(Aravis, GLib)`` from PyGObject (pip ``PyGObject``, else Debian's ``python3-gi``).

    Raises
    ------
    AravisUnavailable
        With the install steps, when either is missing.
    """
    try:
        try:
            import gi
        except ImportError:
            gi = _load_debian_gi()
        gi.require_version("Aravis", "0.8")
        from gi.repository import Aravis, GLib
    except (ImportError, ValueError) as exc:
        raise AravisUnavailable(f"{INSTALL_HINT} ({exc})") from None
    return Aravis, GLib


def aravis_available() -> str | None:
    """``None`` when Aravis can be used, else the reason it cannot."""
    try:
        import_aravis()
    except AravisUnavailable as exc:
        return str(exc)
    return None


def list_cameras() -> list[dict[str, str]]:
    """The GenICam devices Aravis discovers (GigE Vision on every interface, USB3 Vision)."""
    Aravis, _ = import_aravis()
    Aravis.update_device_list()
    out = []
    for i in range(Aravis.get_n_devices()):
        out.append({"id": Aravis.get_device_id(i), "vendor": Aravis.get_device_vendor(i) or "",
                    "model": Aravis.get_device_model(i) or "",
                    "serial": Aravis.get_device_serial_nbr(i) or "",
                    "address": Aravis.get_device_address(i) or "",
                    "protocol": Aravis.get_device_protocol(i) or ""})
    return out
