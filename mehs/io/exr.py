"""OpenEXR images: RGB (half or float), grayscale and multi-channel spectral.

Built on the OpenEXR 3.x Python bindings (``OpenEXR.File`` with a channel
dict). Every write goes through :func:`mehs.io.atomic.atomic_path` (the
temporary name keeps the ``.exr`` suffix); every read checks the magic number,
the channel sampling and (by default) that no pixel is NaN or infinite.

Channel order
    EXR files store channels sorted by name. So that a write→read round trip
    gives the channels back in the order they were written, the writer records
    that order in the string-vector attribute ``mehsChannelOrder``. Files from
    other tools are read in a conventional order: ``R, G, B, A`` (per layer)
    first, spectral channels by wavelength, anything else by name.

Spectral layout (Fichet, Pacanowski & Wilkie 2021)
    One channel per band named ``S0.<λ>nm`` for emissive data (radiance; the
    unpolarised Stokes component S0) or ``T.<λ>nm`` for reflectance /
    transmittance, where ``<λ>`` is the band centre in nm written with a comma
    as decimal separator and the shortest digits that round-trip exactly, e.g.
    ``S0.400nm``, ``S0.397,32nm``. Header attributes: ``spectralLayoutVersion
    = "1.0"`` (Fichet 2021), ``wavelengths`` (float vector, nm, band order),
    ``mehsWavelengths`` (the same as exact decimal text), ``mehsFWHM`` (text,
    when known), ``mehsUnits`` (the cube's units). Readers that know the
    Fichet layout (colour-science ``read_spectral_image_Fichet2021``, the
    spectral-exr viewer, ART) read these files; the reader here also accepts
    bare ``<λ>nm`` channel names.

References
----------
- Kainz, Bogart, Stanczyk, Hillman. *Technical Introduction to OpenEXR*
  (channel naming, half-float range).
- Fichet, A., Pacanowski, R., & Wilkie, A. (2021). An OpenEXR Layout for
  Spectral Images. JCGT 10(3). http://jcgt.org/published/0010/03/01/
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from mehs.errors import FormatError, InputError
from mehs.io.atomic import atomic_path

#: The first four bytes of every OpenEXR file (0x762f3101, little-endian).
EXR_MAGIC = b"\x76\x2f\x31\x01"

#: Largest finite half-float value.
HALF_MAX = 65504.0
FLOAT32_MAX = float(np.finfo(np.float32).max)

#: Header attribute recording the written channel order.
ORDER_ATTR = "mehsChannelOrder"

_UNIT_TO_NM = {"": 1e9, "m": 1e6, "u": 1e3, "n": 1.0, "p": 1e-3}
# Fichet 2021 channel: component (S0..S3 or T), '.', number with ',' decimal, unit.
_SPECTRAL_RE = re.compile(
    r"^(?:(?P<comp>S[0-3]|T)\.)?(?P<num>\d+(?:[,.]\d*)?(?:[eE][-+]?\d+)?)(?P<mult>[munp]?)m$")
_RGBA_ORDER = {"R": 0, "G": 1, "B": 2, "A": 3}


@dataclass
class ExrImage:
    """An OpenEXR image read into memory.

    Attributes
    ----------
    data
        float32 array of shape ``(H, W, C)`` (half channels are widened).
    channels
        The ``C`` channel names, in the order of the last axis of ``data``.
    header
        The file's header attributes (as the OpenEXR bindings return them),
        without the ``channels`` entry.
    path
        The file that was read.
    """

    data: np.ndarray
    channels: list[str]
    header: dict[str, Any] = field(default_factory=dict)
    path: Path | None = None

    def channel(self, name: str) -> np.ndarray:
        """The ``(H, W)`` plane of channel ``name``."""
        try:
            return self.data[:, :, self.channels.index(name)]
        except ValueError:
            raise InputError(f"no channel {name!r} (has {self.channels})", self.path) from None


# --------------------------------------------------------------------------- writing

def write_exr(path: str | Path, image: np.ndarray, channels: Sequence[str] | None = None, *,
              half: bool = False, header: dict[str, Any] | None = None) -> Path:
    """Write an image with any number of channels as a single-part scan-line EXR.

    Parameters
    ----------
    path
        Destination ``.exr`` file; written atomically (temp + rename).
    image
        ``(H, W)`` or ``(H, W, C)`` array, any real dtype.
    channels
        ``C`` unique channel names. Default: ``Y`` for one channel, ``R, G, B``
        for three, ``R, G, B, A`` for four; required otherwise.
    half
        Store 16-bit half floats instead of 32-bit floats.
    header
        Extra header attributes (str, float, int, list of float/str, …).

    Returns
    -------
    Path
        ``path``.

    Raises
    ------
    InputError
        Non-finite values, values beyond the half-float range when ``half``,
        a wrong shape or channel list.
    """
    import OpenEXR

    path = Path(path)
    img = np.asarray(image)
    if img.ndim == 2:
        img = img[:, :, None]
    if img.ndim != 3 or img.shape[0] == 0 or img.shape[1] == 0 or img.shape[2] == 0:
        raise InputError(f"an EXR image must be (H, W) or (H, W, C), got shape {np.shape(image)}",
                         path)
    if not np.issubdtype(img.dtype, np.number) or np.iscomplexobj(img):
        raise InputError(f"cannot store dtype {img.dtype} in an EXR", path)
    n = img.shape[2]
    if channels is None:
        defaults = {1: ["Y"], 3: ["R", "G", "B"], 4: ["R", "G", "B", "A"]}
        if n not in defaults:
            raise InputError(f"{n} channels need explicit channel names", path)
        channels = defaults[n]
    channels = [str(c) for c in channels]
    if len(channels) != n:
        raise InputError(f"{len(channels)} channel names for {n} channels", path)
    if len(set(channels)) != n or any(not c for c in channels):
        raise InputError(f"channel names must be unique and non-empty: {channels}", path)

    dtype = np.float16 if half else np.float32
    finite = np.isfinite(img) if img.dtype.kind == "f" else None
    if finite is not None and not finite.all():
        bad = int((~finite).sum())
        raise InputError(f"refusing to write {bad} NaN/Inf values to an EXR", path)
    # a finite float64 beyond float32's range would become Inf in the conversion below
    peak = float(np.abs(img).max()) if img.size else 0.0
    if half and peak > HALF_MAX:
        raise InputError(
            f"value {peak:.6g} exceeds the half-float range (±{HALF_MAX:g}); "
            "write 32-bit float or rescale", path)
    if peak > FLOAT32_MAX:
        raise InputError(f"value {peak:.6g} exceeds the 32-bit float range "
                         f"(±{FLOAT32_MAX:.6g}); rescale", path)

    pixels = {c: np.ascontiguousarray(img[:, :, i], dtype=dtype) for i, c in enumerate(channels)}
    hdr: dict[str, Any] = {"compression": OpenEXR.ZIP_COMPRESSION,
                           "type": OpenEXR.scanlineimage}
    if header:
        hdr.update(header)
    hdr[ORDER_ATTR] = list(channels)
    with atomic_path(path) as tmp:
        try:
            OpenEXR.File(hdr, pixels).write(str(tmp))
        except (RuntimeError, ValueError, TypeError) as exc:
            raise FormatError(f"OpenEXR could not write the image ({exc})", path) from None
    return path


def write_exr_rgb(path: str | Path, rgb: np.ndarray, *, half: bool = True,
                  header: dict[str, Any] | None = None) -> Path:
    """Write a linear RGB image ``(H, W, 3)`` as channels R, G, B (half float by default)."""
    rgb = np.asarray(rgb)
    if rgb.ndim != 3 or rgb.shape[2] != 3:
        raise InputError(f"an RGB image must be (H, W, 3), got shape {rgb.shape}", path)
    return write_exr(path, rgb, ["R", "G", "B"], half=half, header=header)


def write_exr_gray(path: str | Path, img: np.ndarray, *, half: bool = False,
                   header: dict[str, Any] | None = None) -> Path:
    """Write a single-channel image ``(H, W)`` as channel ``Y`` (32-bit float by default)."""
    img = np.asarray(img)
    if img.ndim == 3 and img.shape[2] == 1:
        img = img[:, :, 0]
    if img.ndim != 2:
        raise InputError(f"a grayscale image must be (H, W), got shape {img.shape}", path)
    return write_exr(path, img, ["Y"], half=half, header=header)


def wavelength_channel_name(wavelength_nm: float, component: str = "S0") -> str:
    """Fichet 2021 channel name of one band, e.g. ``S0.400nm`` or ``T.397,32nm``."""
    wl = float(wavelength_nm)
    text = str(int(wl)) if wl.is_integer() else repr(wl)
    return f"{component}.{text.replace('.', ',')}nm"


def write_exr_spectral(path: str | Path, cube: Any, wavelengths: Sequence[float] | None = None, *,
                       half: bool = False, header: dict[str, Any] | None = None) -> Path:
    """Write a spectral image as one EXR channel per band (Fichet 2021 layout).

    Parameters
    ----------
    cube
        A :class:`~mehs.cube.SpectralCube` or an ``(H, W, B)`` array (then
        ``wavelengths`` is required). A cube's lines become image rows.
    wavelengths
        Band centres in nm, ``(B,)``; overrides the cube's when given.
    half
        Store half floats (values beyond ±65504 raise).

    Channels are ``S0.<λ>nm`` (``T.<λ>nm`` when the cube's units say
    reflectance); see the module docstring for the header attributes.
    """
    from mehs.cube import SpectralCube, validate_wavelengths

    path = Path(path)
    units = "relative radiance"
    fwhm = None
    if isinstance(cube, SpectralCube):
        data = cube.data
        wl = cube.wavelengths if wavelengths is None else wavelengths
        units = cube.units
        fwhm = cube.fwhm if wavelengths is None else None
    else:
        data = np.asarray(cube)
        if wavelengths is None:
            raise InputError("wavelengths are required to write an array as a spectral EXR", path)
        wl = wavelengths
    if data.ndim != 3:
        raise InputError(f"a spectral image must be (H, W, B), got shape {data.shape}", path)
    wl = validate_wavelengths(wl, data.shape[2], path)
    component = "T" if "reflect" in str(units).lower() or "transmit" in str(units).lower() else "S0"
    names = [wavelength_channel_name(w, component) for w in wl]
    hdr: dict[str, Any] = {
        "spectralLayoutVersion": "1.0",
        "wavelengths": [float(w) for w in wl],
        "mehsWavelengths": " ".join(repr(float(w)) for w in wl),
        "mehsUnits": str(units),
    }
    if fwhm is not None:
        hdr["mehsFWHM"] = " ".join(repr(float(f)) for f in fwhm)
    if header:
        hdr.update(header)
    return write_exr(path, data, names, half=half, header=hdr)


# --------------------------------------------------------------------------- reading

def _check_file(path: Path) -> None:
    if not path.exists():
        raise InputError("file does not exist", path)
    if path.is_dir():
        raise InputError("is a folder, not an OpenEXR file", path)
    with open(path, "rb") as fh:
        magic = fh.read(4)
    if magic != EXR_MAGIC:
        raise FormatError("not an OpenEXR file (bad magic number)", path)


def _channel_sort_key(name: str) -> tuple:
    layer, _, base = name.rpartition(".")
    m = _SPECTRAL_RE.match(name)
    if m:
        return (1, m.group("comp") or "", _parse_nm(m), name)
    if base in _RGBA_ORDER:
        return (0, layer, _RGBA_ORDER[base], name)
    return (2, name, 0.0, name)


def _parse_nm(m: re.Match) -> float:
    return float(m.group("num").replace(",", ".")) * _UNIT_TO_NM[m.group("mult")]


def read_exr(path: str | Path, *, check_finite: bool = True) -> ExrImage:
    """Read the first part of an OpenEXR file into a float32 ``(H, W, C)`` array.

    Parameters
    ----------
    path
        The ``.exr`` file.
    check_finite
        Raise :class:`InputError` when any pixel is NaN or infinite.

    Returns
    -------
    ExrImage
        ``data`` float32 ``(H, W, C)``, ``channels`` in written order (see
        the module docstring), ``header`` without ``channels``.

    Raises
    ------
    InputError
        Missing file, NaN/Inf values.
    FormatError
        Not an OpenEXR file, a damaged file, sub-sampled channels.
    """
    import OpenEXR

    path = Path(path)
    _check_file(path)
    try:
        f = OpenEXR.File(str(path), separate_channels=True)
        header = dict(f.header())
        chans = f.channels()
    except (RuntimeError, ValueError, OSError) as exc:
        raise FormatError(f"cannot read the OpenEXR file ({exc})", path) from None
    header.pop("channels", None)
    if not chans:
        raise FormatError("the OpenEXR file has no channels", path)
    names = list(chans)
    order = header.get(ORDER_ATTR)
    if isinstance(order, (list, tuple)) and sorted(map(str, order)) == sorted(names):
        names = [str(c) for c in order]
    else:
        names.sort(key=_channel_sort_key)
    planes = []
    for name in names:
        ch = chans[name]
        if (getattr(ch, "xSampling", 1), getattr(ch, "ySampling", 1)) != (1, 1):
            raise FormatError(f"channel {name!r} is sub-sampled; not supported", path)
        planes.append(np.asarray(ch.pixels))
    shapes = {p.shape for p in planes}
    if len(shapes) != 1 or len(next(iter(shapes))) != 2:
        raise FormatError(f"channels have inconsistent shapes {sorted(shapes)}", path)
    data = np.empty(planes[0].shape + (len(planes),), dtype=np.float32)
    for i, p in enumerate(planes):
        data[:, :, i] = p
    if check_finite:
        bad = ~np.isfinite(data)
        if bad.any():
            per = bad.reshape(-1, data.shape[2]).sum(axis=0)
            worst = [f"{names[i]}: {int(per[i])}" for i in np.flatnonzero(per)[:5]]
            raise InputError(f"{int(bad.sum())} NaN/Inf pixel values ({', '.join(worst)})", path)
    return ExrImage(data=data, channels=names, header=header, path=path)


def spectral_channels(channels: Sequence[str]) -> tuple[list[int], np.ndarray]:
    """Indices and wavelengths (nm) of the emissive/reflective spectral channels.

    Recognises Fichet 2021 names (``S0.<λ>nm``, ``T.<λ>nm``, units ``m``,
    ``um``, ``nm``, ``pm``; comma or point decimal) and bare ``<λ>nm``.
    Polarised components ``S1``–``S3`` are skipped. When both ``S0`` and
    ``T`` channels exist, ``S0`` (emission) wins.
    """
    found: dict[str, list[tuple[int, float]]] = {}
    for i, name in enumerate(channels):
        m = _SPECTRAL_RE.match(name)
        if m and m.group("comp") in (None, "S0", "T"):
            found.setdefault(m.group("comp") or "", []).append((i, _parse_nm(m)))
    for comp in ("S0", "T", ""):
        if comp in found:
            idx, wl = zip(*found[comp])
            return list(idx), np.asarray(wl, dtype=np.float64)
    return [], np.empty(0)


def _text_floats(value: Any, n: int) -> np.ndarray | None:
    if not isinstance(value, str):
        return None
    try:
        out = np.asarray([float(v) for v in value.split()], dtype=np.float64)
    except ValueError:
        return None
    return out if out.size == n else None


def read_exr_spectral(path: str | Path):
    """Read a spectral EXR (Fichet 2021 layout or bare ``<λ>nm`` channels).

    Returns
    -------
    SpectralCube
        float32 data ``(H, W, B)`` (rows → lines), wavelengths from the
        exact ``mehsWavelengths`` attribute when present and consistent, else
        from the channel names; units from ``mehsUnits`` (default
        ``"relative radiance"``, or ``"reflectance"`` for ``T.`` channels).
        Non-spectral channels (e.g. an ``R, G, B`` preview) are ignored.

    Raises
    ------
    FormatError
        No spectral channels.
    """
    from mehs.cube import SpectralCube

    img = read_exr(path, check_finite=True)
    idx, wl = spectral_channels(img.channels)
    if not idx:
        raise FormatError(
            f"no spectral channels (expected names like 'S0.400nm'); channels are "
            f"{img.channels[:8]}{'…' if len(img.channels) > 8 else ''}", img.path)
    exact = _text_floats(img.header.get("mehsWavelengths"), len(idx))
    if exact is not None and np.allclose(exact, wl, rtol=0, atol=1e-3):
        wl = exact
    comp = _SPECTRAL_RE.match(img.channels[idx[0]]).group("comp")
    units = img.header.get("mehsUnits")
    if not isinstance(units, str):
        units = "reflectance" if comp == "T" else "relative radiance"
    fwhm = _text_floats(img.header.get("mehsFWHM"), len(idx))
    data = img.data if idx == list(range(img.data.shape[2])) else img.data[:, :, idx]
    return SpectralCube(data=np.ascontiguousarray(data), wavelengths=wl, fwhm=fwhm, units=units,
                        source=img.path, metadata={"exr_channels": [img.channels[i] for i in idx]})
