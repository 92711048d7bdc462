"""What the ENVI reader and writer share: layout keys, data types, acquisition dates.

(:mod:`mehs.io.envi` reads, :mod:`mehs.io.envi_write` writes; both import from here.)
"""

from __future__ import annotations

import re
from datetime import date, datetime, timedelta, timezone

import numpy as np

INTERLEAVES = ("bil", "bip", "bsq")

#: Keys the reader turns into cube fields and the writer regenerates from them;
#: they are never copied from ``cube.metadata`` into a written header.
MANAGED_KEYS = frozenset({
    "samples", "lines", "bands", "header offset", "data type", "interleave",
    "byte order", "file type", "wavelength", "fwhm", "wavelength units", "tint",
    "acquisition date", "default bands", "binning", "reflectance scale factor",
    "data units", "dark subtracted",
})
STRUCTURAL_KEYS = frozenset({"samples", "lines", "bands", "header offset",
                              "data type", "interleave", "byte order", "file type"})


#: ``wavelength units`` (lower case) → factor to nanometres.
UNIT_SCALE = {"nanometers": 1.0, "nanometer": 1.0, "nanometres": 1.0, "nanometre": 1.0,
               "nm": 1.0, "micrometers": 1e3, "micrometer": 1e3, "micrometres": 1e3,
               "micrometre": 1e3, "microns": 1e3, "micron": 1e3, "um": 1e3, "µm": 1e3,
               "millimeters": 1e6, "millimeter": 1e6, "mm": 1e6, "centimeters": 1e7,
               "centimeter": 1e7, "cm": 1e7, "meters": 1e9, "meter": 1e9, "m": 1e9,
               "angstroms": 0.1, "angstrom": 0.1, "å": 0.1}


#: Without a (known) ``wavelength units``, band centres all below this are micrometres:
#: imaging spectrometers reach 14 µm (thermal infrared) and none records below 100 nm.
MAX_MICROMETRES = 100.0


def units_mismatch(wl_nm: np.ndarray, scale: float, unit: str, said: str) -> str | None:
    """Why band centres ``wl_nm`` (converted by ``scale`` from the header's ``unit``,
    written ``said``) cannot be what the header meant, or None.

    No imaging spectrometer records beyond 100 µm (far infrared) or below 100 nm
    (X-rays): 400–1000 labelled "Micrometers" are nanometres, 0.4–1.0 labelled
    "Nanometers" micrometres — the data are fine, the units line is wrong.
    """
    if np.any(wl_nm > MAX_MICROMETRES * 1e3):
        return (f"band centres up to {wl_nm.max() / 1e3:g} µm: the wavelength units {said!r} "
                f"do not fit values {wl_nm.min() / scale:g}–{wl_nm.max() / scale:g} "
                "(nanometres?); correct the 'wavelength units' line")
    raw = wl_nm / scale
    whole = np.all(np.abs(raw - np.round(raw)) <= 1e-9 * np.maximum(np.abs(raw), 1.0))
    if unit in UNIT_SCALE and np.all(wl_nm < 100.0) and not whole:
        # whole numbers are band indices (the reader's rule for unknown units, and what
        # mehs writes back, labelled Nanometers, from a header in 'Index' units): kept
        return (f"band centres {wl_nm.min():g}–{wl_nm.max():g} nm are X-rays: the wavelength "
                f"units {said!r} do not fit values {wl_nm.min() / scale:g}–"
                f"{wl_nm.max() / scale:g} (micrometres?); correct the 'wavelength units' line")
    return None


def envi_dtypes() -> dict[str, np.dtype]:
    """ENVI ``data type`` codes → numpy dtypes (SPy's table)."""
    from spectral.io.envi import envi_to_dtype

    return {k: np.dtype(v) for k, v in envi_to_dtype.items()}


_DATE_FORMATS = {"dd-mm-yyyy": "%d-%m-%Y", "yyyy-mm-dd": "%Y-%m-%d",
                 "mm-dd-yyyy": "%m-%d-%Y", "dd.mm.yyyy": "%d.%m.%Y",
                 "dd/mm/yyyy": "%d/%m/%Y", "yyyy/mm/dd": "%Y/%m/%d"}
_TIME_RE = re.compile(r"^(\d{1,2}):(\d{2})(?::(\d{2})(?:\.(\d{1,6}))?)?"
                      r"(Z|[+-]\d{2}:?\d{2})?$")


def parse_acquisition_date(text: str) -> str | None:
    """ISO-8601 form of an ENVI/Specim ``acquisition date`` value, or ``None``.

    Accepts ``DD-MM-YYYY``, ``YYYY-MM-DD``, ``DATE(dd-mm-yyyy): DD-MM-YYYY``,
    ``DATE(yyyy-mm-dd): YYYY-MM-DD`` and ISO date-times, each optionally
    followed by ``HH:MM[:SS[.ffffff]][Z|±HH:MM]``. Returns ``YYYY-MM-DD`` or
    ``YYYY-MM-DDTHH:MM:SS[.ffffff]``.
    """
    s = str(text).strip()
    fmts: list[str]
    m = re.match(r"^DATE\s*\(\s*([A-Za-z./-]+)\s*\)\s*:?\s*(.*)$", s, re.IGNORECASE)
    if m:
        key = m.group(1).lower()
        if key not in _DATE_FORMATS:
            return None
        fmts, s = [_DATE_FORMATS[key]], m.group(2).strip()
    else:
        fmts = ["%d-%m-%Y", "%Y-%m-%d", "%d.%m.%Y", "%Y/%m/%d"]
    if not m:
        try:
            return datetime.fromisoformat(s).isoformat() if "T" in s \
                else date.fromisoformat(s).isoformat()
        except ValueError:
            pass
    parts = s.replace("T", " ").split()
    if not parts or len(parts) > 2:
        return None
    day = None
    for f in fmts:
        try:
            day = datetime.strptime(parts[0], f).date()
            break
        except ValueError:
            continue
    if day is None:
        return None
    if len(parts) == 1:
        return day.isoformat()
    t = _TIME_RE.match(parts[1])
    if not t:
        return None
    hh, mm, ss = int(t.group(1)), int(t.group(2)), int(t.group(3) or 0)
    us = int((t.group(4) or "0").ljust(6, "0"))
    tz = None
    if t.group(5):
        z = t.group(5).replace(":", "")
        off = 0 if z == "Z" else (int(z[1:3]) * 60 + int(z[3:5])) * (1 if z[0] == "+" else -1)
        tz = timezone(timedelta(minutes=off))
    try:
        return datetime(day.year, day.month, day.day, hh, mm, ss, us, tzinfo=tz).isoformat()
    except ValueError:
        return None


def format_acquisition_date(iso: str) -> str:
    """Specim-style header value for an ISO date: ``DATE(dd-mm-yyyy): DD-MM-YYYY[ HH:MM:SS]``.

    A value that is not ISO is returned unchanged.
    """
    try:
        dt = datetime.fromisoformat(iso)
    except (TypeError, ValueError):
        return str(iso)
    out = f"DATE(dd-mm-yyyy): {dt:%d-%m-%Y}"
    if "T" in iso or " " in iso.strip():
        out += f" {dt:%H:%M:%S}" + (f".{dt.microsecond:06d}" if dt.microsecond else "")
        if dt.utcoffset() is not None:
            out += dt.isoformat()[-6:]  # "+HH:MM"; Specim has none, mehs keeps it
    return out


def reflectance_scale(fields: dict, hp) -> float | None:
    """The header's ``reflectance scale factor`` (None when absent); a value that is not a
    finite non-zero number is a :class:`~mehs.errors.FormatError` naming ``hp``: dividing
    by it would give Inf or NaN reflectances, or ``abc`` no number at all."""
    from mehs.errors import FormatError

    if "reflectance scale factor" not in fields:
        return None
    raw = fields["reflectance scale factor"]
    try:
        sf = float(str(raw).strip())
    except ValueError:
        sf = float("nan")
    if not (np.isfinite(sf) and sf != 0):
        raise FormatError(f"reflectance scale factor {raw!r} must be a non-zero number", hp)
    return sf
