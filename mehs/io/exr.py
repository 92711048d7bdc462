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

Spectral images
    One channel per band (Fichet, Pacanowski & Wilkie 2021 layout):
    :mod:`mehs.io.exr_spectral`, whose functions are re-exported here. The
    names of spectral channels are parsed here (:func:`parse_spectral_channel`)
    because the conventional order above needs them.

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

#: Smallest positive half float (subnormal), 2^-24 ≈ 6.0e-8; 2^-14 is the smallest normal.
HALF_TINY = 2.0 ** -24

#: Fraction of the non-zero values a half-float write may flush to 0 before it warns: a few
#: noise samples next to 0 (a fused cube keeps its signed estimates) are no loss, a region is.
HALF_UNDERFLOW_WARN_FRACTION = 1e-4


class HalfFloatUnderflowWarning(UserWarning):
    """A half-float EXR write stored a region of non-zero values as 0 (below 2^-25)."""

#: SI prefixes of Fichet 2021's channel quantities, as powers of ten (``u``/``µ``: micro).
_SI_EXP = {"Y": 24, "Z": 21, "E": 18, "P": 15, "T": 12, "G": 9, "M": 6, "k": 3, "h": 2,
           "da": 1, "": 0, "d": -1, "c": -2, "m": -3, "u": -6, "\u00b5": -6, "\u03bc": -6,
           "n": -9, "p": -12, "f": -15, "a": -18, "z": -21, "y": -24}
#: Speed of light in vacuum (m/s, exact by the SI): a channel named by its frequency
_LIGHT_SPEED = 299792458.0
_QUANTITY = (r"(?P<num>\d+(?:[,.]\d*)?(?:[eE][-+]?\d+)?)"
             r"(?P<mult>da|[YZEPTGMkhdcmu\u00b5\u03bcnpfazy]?)(?P<unit>m|Hz)")
# Fichet 2021 channel: component (S0..S3 or T), '.', a wavelength or frequency with ','
# decimal and an SI prefix (``S0.400nm``, ``S0.0,4um``, ``T.749,48THz``).
_SPECTRAL_RE = re.compile(r"^(?:(?P<comp>S[0-3]|T)\.)?" + _QUANTITY + "$")
# Fichet 2021 bi-spectral (re-radiation) channel: ``T.<λ in>.<λ out>``
BISPECTRAL_RE = re.compile(r"^T\." + _QUANTITY.replace("?P<", "?P<i") + r"\."
                           + _QUANTITY.replace("?P<", "?P<o") + "$")
# KAIST (Choi et al. 2017): ``w420nm`` … ``w720nm`` (a decimal centre is accepted).
_KAIST_RE = re.compile(r"^w(?P<num>\d+(?:\.\d+)?)nm$")
#: Naming schemes of spectral channels (:func:`parse_spectral_channel`): Fichet 2021
#: components, bare ``<λ>nm``, KAIST ``w<λ>nm``.
SCHEME_BARE, SCHEME_KAIST = "", "w"
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
              half: bool = False, header: dict[str, Any] | None = None,
              name: str | Path | None = None) -> Path:
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
    name
        The file to name in errors and warnings, when ``path`` is a caller's temporary
        file that is renamed onto it later (default: ``path``).

    Returns
    -------
    Path
        ``path``.

    Raises
    ------
    InputError
        Non-finite values, values beyond the half-float range when ``half``,
        a wrong shape or channel list.

    Warns
    -----
    HalfFloatUnderflowWarning
        ``half`` and more than 1e-4 of the non-zero values below 2^-25 (stored as 0;
        counted in the header either way, see :func:`_half_underflow`).
    """
    import OpenEXR

    path = Path(path)
    where = Path(name) if name is not None else path
    img = np.asarray(image)
    if img.ndim == 2:
        img = img[:, :, None]
    if img.ndim != 3 or img.shape[0] == 0 or img.shape[1] == 0 or img.shape[2] == 0:
        raise InputError(f"an EXR image must be (H, W) or (H, W, C), got shape {np.shape(image)}",
                         where)
    if not np.issubdtype(img.dtype, np.number) or np.iscomplexobj(img):
        raise InputError(f"cannot store dtype {img.dtype} in an EXR", where)
    n = img.shape[2]
    if channels is None:
        defaults = {1: ["Y"], 3: ["R", "G", "B"], 4: ["R", "G", "B", "A"]}
        if n not in defaults:
            raise InputError(f"{n} channels need explicit channel names", where)
        channels = defaults[n]
    channels = [str(c) for c in channels]
    if len(channels) != n:
        raise InputError(f"{len(channels)} channel names for {n} channels", where)
    if len(set(channels)) != n or any(not c for c in channels):
        raise InputError(f"channel names must be unique and non-empty: {channels}", where)

    dtype = np.float16 if half else np.float32
    finite = np.isfinite(img) if img.dtype.kind == "f" else None
    if finite is not None and not finite.all():
        bad = int((~finite).sum())
        raise InputError(f"refusing to write {bad} NaN/Inf values to an EXR", where)
    # a finite float64 beyond float32's range would become Inf in the conversion below
    peak = float(np.abs(img).max()) if img.size else 0.0
    if half and peak > HALF_MAX:
        raise InputError(
            f"value {peak:.6g} exceeds the half-float range (±{HALF_MAX:g}); "
            "write 32-bit float or rescale", where)
    if peak > FLOAT32_MAX:
        raise InputError(f"value {peak:.6g} exceeds the 32-bit float range "
                         f"(±{FLOAT32_MAX:.6g}); rescale", where)

    pixels = {c: np.ascontiguousarray(img[:, :, i], dtype=dtype) for i, c in enumerate(channels)}
    hdr: dict[str, Any] = {"compression": OpenEXR.ZIP_COMPRESSION,
                           "type": OpenEXR.scanlineimage}
    if header:
        hdr.update(header)
    if half:
        hdr.update(_half_underflow(img, pixels, channels, where))
    hdr[ORDER_ATTR] = list(channels)
    with atomic_path(path) as tmp:
        try:
            OpenEXR.File(hdr, pixels).write(str(tmp))
        except (RuntimeError, ValueError, TypeError) as exc:
            raise FormatError(f"OpenEXR could not write the image ({exc})", where) from None
    return path


def _half_underflow(img: np.ndarray, pixels: dict[str, np.ndarray], channels: list[str],
                    path: Path) -> dict[str, int]:
    """Header attributes (and a warning) for the values a half-float write loses at the low end.

    Policy: binary16 has nothing between 0 and 2^-24 but rounding, so a non-zero value below
    2^-25 is stored as 0 and one below 2^-14 as a subnormal (fewer than 11 significant bits).
    Both are counted into the header (``mehsHalfFlushedToZero``, ``mehsHalfSubnormal``, only
    when non-zero); when more than :data:`HALF_UNDERFLOW_WARN_FRACTION` of the non-zero values
    become 0, a :class:`HalfFloatUnderflowWarning` names the file, so a picture whose dim part
    vanished is never silent. Callers that control the range store ``value × 2^k``
    (:func:`mehs.dataset.cube_figures.half_float_scale`) so that this does not happen.
    """
    import warnings

    flushed = subnormal = nonzero = 0
    largest = 0.0
    for i, c in enumerate(channels):
        src, half = img[:, :, i], pixels[c]
        nz = src != 0
        lost = nz & (half == 0)
        flushed += int(lost.sum())
        nonzero += int(nz.sum())
        subnormal += int(((half != 0) & (np.abs(half) < np.float16(2.0 ** -14))).sum())
        if lost.any():
            largest = max(largest, float(np.abs(src[lost]).max()))
    out = {}
    if flushed:
        out["mehsHalfFlushedToZero"] = flushed
        if flushed > HALF_UNDERFLOW_WARN_FRACTION * nonzero:
            warnings.warn(HalfFloatUnderflowWarning(
                f"{path}: {flushed} non-zero values ({100.0 * flushed / nonzero:.3g} % of them, "
                f"up to {largest:.3g}) lie below the half-float range (smallest value "
                f"{HALF_TINY:.3g}) and are stored as 0; scale the image up (×2^k) or write "
                f"32-bit float"), stacklevel=3)
    if subnormal:
        out["mehsHalfSubnormal"] = subnormal
    return out


def half_underflow_counts(paths) -> dict[str, int]:
    """``{"half_flushed_to_zero", "half_subnormal"}``: the values the half-float EXRs
    ``paths`` stored as 0 / as subnormals, summed, as :func:`write_exr` counted them into
    their headers (``mehsHalfFlushedToZero``, ``mehsHalfSubnormal``, absent when 0)."""
    import OpenEXR

    out = {"half_flushed_to_zero": 0, "half_subnormal": 0}
    for path in paths:
        header = OpenEXR.File(str(path), header_only=True).header()
        out["half_flushed_to_zero"] += int(header.get("mehsHalfFlushedToZero", 0))
        out["half_subnormal"] += int(header.get("mehsHalfSubnormal", 0))
    return out


def write_exr_rgb(path: str | Path, rgb: np.ndarray, *, half: bool = True,
                  header: dict[str, Any] | None = None) -> Path:
    """Write a linear RGB image ``(H, W, 3)`` as channels R, G, B (half float by default)."""
    rgb = np.asarray(rgb)
    if rgb.ndim != 3 or rgb.shape[2] != 3:
        raise InputError(f"an RGB image must be (H, W, 3), got shape {rgb.shape}", path)
    return write_exr(path, rgb, ["R", "G", "B"], half=half, header=header)


def write_exr_gray(path: str | Path, img: np.ndarray, *, half: bool = False,
                   header: dict[str, Any] | None = None, name: str | Path | None = None) -> Path:
    """Write a single-channel image ``(H, W)`` as channel ``Y`` (32-bit float by default)."""
    img = np.asarray(img)
    if img.ndim == 3 and img.shape[2] == 1:
        img = img[:, :, 0]
    if img.ndim != 2:
        raise InputError(f"a grayscale image must be (H, W), got shape {img.shape}",
                         name or path)
    return write_exr(path, img, ["Y"], half=half, header=header, name=name)


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


def parse_spectral_channel(name: str) -> tuple[str, float] | None:
    """The naming scheme and band centre (nm) of a spectral channel name, else ``None``.

    The one parser of spectral channel names in mehs (the generic reader here and the
    KAIST reader of :mod:`mehs.io.ssr_kaist`). Schemes: ``"S0"`` … ``"S3"`` and ``"T"``
    (Fichet 2021: ``S0.400nm``, ``T.397,32nm``, ``S0.0,4um``, or a frequency with any SI
    prefix, ``S0.749,48THz`` → c/ν = 400 nm), :data:`SCHEME_BARE` (``400nm``) and
    :data:`SCHEME_KAIST` (``w420nm``).
    """
    name = str(name)
    m = _SPECTRAL_RE.match(name)
    if m:
        nm = _quantity_nm(m.group("num"), m.group("mult"), m.group("unit"))
        return None if nm is None else ((m.group("comp") or SCHEME_BARE), nm)
    m = _KAIST_RE.match(name)
    if m:
        return SCHEME_KAIST, float(m.group("num"))
    return None


def _quantity_nm(num: str, mult: str, unit: str) -> float | None:
    """Wavelength (nm) of a channel's quantity: a wavelength, or a frequency (λ = c/ν)."""
    v = float(num.replace(",", "."))
    e = _SI_EXP[mult]
    if unit == "m":
        return v * 10.0 ** (e + 9)      # exact for nm (10**0) and um
    v *= 10.0 ** e
    return _LIGHT_SPEED / v * 1e9 if v > 0 else None


def _channel_sort_key(name: str) -> tuple:
    layer, _, base = name.rpartition(".")
    parsed = parse_spectral_channel(name)
    if parsed:
        return (1, parsed[0], parsed[1], name)
    if base in _RGBA_ORDER:
        return (0, layer, _RGBA_ORDER[base], name)
    return (2, name, 0.0, name)


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


# the spectral layout lives in its own module (size); its names stay importable from
# here, looked up on first use (PEP 562): importing them at the end of this module made
# ``import mehs.io.exr_spectral`` fail with a circular ImportError in a fresh process
_SPECTRAL_NAMES = frozenset({"ABSOLUTE_RADIANCE", "EMISSIVE_UNITS", "checked_spectral_channels",
                             "read_exr_spectral", "spectral_channels",
                             "wavelength_channel_name", "write_exr_spectral"})


def __getattr__(name: str):
    if name in _SPECTRAL_NAMES:
        from mehs.io import exr_spectral

        return getattr(exr_spectral, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
