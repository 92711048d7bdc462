"""ENVI cubes: validated, memory-mapped reading and atomic, chunked writing.

Reading is here; writing is :mod:`mehs.io.envi_write` (re-exported as
:func:`write_envi`); what both need is :mod:`mehs.io.envi_keys`.

The ENVI data-type table and header writing
(:func:`spectral.io.envi.write_envi_header`) come from SPy. The data itself is
mapped with :class:`numpy.memmap` exactly as SPy's ``open_memmap`` does, but
after mehs has checked the header and the file size itself — SPy's image
classes keep an open file handle per image, turn a failed memmap into ``None``
and require keys (``byte order``) that real files omit, so validating first
and mapping directly gives clear errors instead of wrong numbers. The header
text itself is parsed with SPy's rules (:mod:`mehs.io.envi_text`), because SPy's
``read_envi_header`` refuses headers that real software writes (a UTF-8
byte-order mark, code-page-1252 bytes).

Orientation
    Every cube is returned as ``(lines, samples, bands)`` whatever the file's
    interleave (``bil``: file order (lines, bands, samples); ``bsq``: (bands,
    lines, samples); ``bip``: (lines, samples, bands)). For ``bil``/``bsq`` the
    result is a transposed *view* of the memmap, not a copy.

Header keys understood on reading (keys are case-insensitive)
    ``samples``, ``lines``, ``bands``, ``data type`` (mandatory);
    ``interleave`` (mandatory unless ``bands = 1``); ``byte order`` (default
    0 = little-endian, with a warning for multi-byte types); ``header offset``
    (default 0, as ENVI); ``wavelength`` / ``fwhm`` with ``wavelength units``
    (nanometres; micrometres are converted, and so are centres all below 100
    when the units are missing or ``Unknown``); ``reflectance scale factor``
    (data are divided by it → float32); Specim keys ``tint`` (integration time,
    ms), ``acquisition date`` (``DD-MM-YYYY``, ``YYYY-MM-DD``,
    ``DATE(dd-mm-yyyy): …``, ``DATE(yyyy-mm-dd): …``, ISO; with an optional
    ``HH:MM:SS``), ``default bands`` (1-based), ``binning``; mehs keys
    ``data units`` and ``dark subtracted``. Everything else is kept in
    ``cube.metadata`` and written back.

References
----------
- NV5 Geospatial (Harris), *ENVI Header Files* — https://www.nv5geospatialsoftware.com/docs/ENVIHeaderFiles.html
- Boggs, T. *Spectral Python (SPy)* — https://www.spectralpython.net/
- Specim IQ user manual, chapter "Data format" (capture folder and header keys).
"""

from __future__ import annotations

import os
import re
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from mehs.cube import SpectralCube, validate_wavelengths
from mehs.errors import FormatError, InputError
from mehs.io.envi_keys import (INTERLEAVES, MANAGED_KEYS, MAX_MICROMETRES, UNIT_SCALE,
                               envi_dtypes, format_acquisition_date, parse_acquisition_date,
                               reflectance_scale, units_mismatch)
from mehs.io.envi_text import read_header_pairs
from mehs.io.envi_write import write_envi  # the writer, part of this module's interface
from mehs.io.plausibility import ByteOrderWarning, byte_order_message, byte_order_suspicion

__all__ = ["EnviHeader", "read_envi_header", "read_envi", "write_envi",
           "data_file_candidates", "find_data_file", "find_header_file", "parse_acquisition_date",
           "format_acquisition_date", "DATA_EXTENSIONS"]

#: Data-file extensions tried after the header's stem (then upper-case), in order.
#: ``.hyspex``: HySpex cameras write ``x.hyspex`` (its own binary header skipped by
#: the ENVI ``header offset``) beside ``x.hdr``.
DATA_EXTENSIONS = ("", ".raw", ".dat", ".img", ".bil", ".bsq", ".bip", ".bin", ".hyspex")

#: axes permutation from a file's (interleave) order to (lines, samples, bands)
_TO_BIP = {"bil": (0, 2, 1), "bsq": (1, 2, 0), "bip": (0, 1, 2)}


@dataclass(frozen=True)
class EnviHeader:
    """A checked ENVI header and the data file it describes.

    ``fields`` holds every header key (lower-cased) with its raw value (a
    string, or a list of strings for ``{…}`` values). ``dtype`` carries the
    file's byte order.
    """

    header_path: Path
    data_path: Path
    lines: int
    samples: int
    bands: int
    dtype: np.dtype
    interleave: str
    byte_order: int
    header_offset: int
    fields: dict[str, Any] = field(default_factory=dict)

    @property
    def shape(self) -> tuple[int, int, int]:
        """``(lines, samples, bands)``."""
        return (self.lines, self.samples, self.bands)

    @property
    def nbytes(self) -> int:
        return self.lines * self.samples * self.bands * self.dtype.itemsize

    def open_memmap(self) -> np.ndarray:
        """Read-only memmap view of the data, shape ``(lines, samples, bands)``.

        Values keep the file's byte order (``dtype`` may be non-native); no
        scale factor is applied. Nothing is read until elements are accessed.
        """
        file_shape = {"bil": (self.lines, self.bands, self.samples),
                      "bsq": (self.bands, self.lines, self.samples),
                      "bip": (self.lines, self.samples, self.bands)}[self.interleave]
        if self.nbytes == 0:  # pragma: no cover - excluded by header checks
            return np.zeros(self.shape, self.dtype)
        mm = np.memmap(self.data_path, dtype=self.dtype, mode="r",
                       offset=self.header_offset, shape=file_shape)
        # (SPy's interleave_transpose returns (1, 1, 1) for "bip"→"bip", so not used.)
        return mm.transpose(_TO_BIP[self.interleave])


# --------------------------------------------------------------------- reading


def header_files(folder: str | Path) -> list[Path]:
    """``folder``'s ENVI headers, sorted, ``.hdr`` in any case (FAT/Windows copies: x.HDR)."""
    folder = Path(folder)
    if not folder.is_dir():
        return []
    return sorted(p for p in folder.iterdir() if p.suffix.lower() == ".hdr" and p.is_file())


def find_header_file(path: str | Path) -> Path:
    """The ``.hdr`` belonging to ``path`` (a header or an ENVI data file)."""
    p = Path(path)
    if p.is_dir():
        raise InputError("is a folder, not an ENVI file", p)
    if p.suffix.lower() == ".hdr":
        if not p.is_file():
            raise InputError("file does not exist", p)
        return p
    if not p.exists():
        raise InputError("file does not exist", p)
    # ENVI names the header either <stem>.hdr or <data name>.hdr.
    for cand in (p.with_suffix(".hdr"), p.with_suffix(".HDR"),
                 p.with_name(p.name + ".hdr"), p.with_name(p.name + ".HDR")):
        if cand.is_file():
            return cand
    raise FormatError("no ENVI header found (looked for "
                      f"{p.with_suffix('.hdr').name} and {p.name}.hdr)", p)


def data_file_candidates(header_path: str | Path, interleave: str | None = None) -> list[Path]:
    """Every existing file that could be an ENVI header's data: its stem with a known
    extension (``DATA_EXTENSIONS``, either case), one entry per distinct file."""
    hp = Path(header_path)
    stem = hp.with_suffix("")
    exts = list(DATA_EXTENSIONS)
    if interleave and f".{interleave}" not in exts:
        exts.append(f".{interleave}")
    found: list[Path] = []
    for ext in exts + [e.upper() for e in exts if e]:
        cand = stem.with_name(stem.name + ext)
        if not cand.is_file() or cand == hp:
            continue
        # (x.raw and x.RAW are one file on a case-insensitive file system)
        if any(os.path.samefile(cand, f) for f in found):
            continue
        found.append(cand)
    return found


def find_data_file(header_path: str | Path, interleave: str | None = None) -> Path:
    """The data file of an ENVI header: the one file with its stem and a known extension.

    Raises
    ------
    FormatError
        None found, or several (an ENVI header does not name its data file, so which
        one is meant cannot be told: open the data file itself, e.g.
        ``read_envi("x.img")``, or remove the stale one).
    """
    hp = Path(header_path)
    found = data_file_candidates(hp, interleave)
    if len(found) == 1:
        return found[0]
    if found:
        raise FormatError(
            f"several files could be this header's data ({', '.join(f.name for f in found)}); "
            "open the data file itself, or remove the stale one", hp)
    stem = hp.with_suffix("")
    tried = [stem.name + e for e in DATA_EXTENSIONS]
    raise FormatError(f"data file not found (tried {', '.join(tried[:8])}, …)", hp)


def _int_field(h: dict, key: str, hp: Path, *, default: int | None = None,
               minimum: int = 1) -> int:
    if key not in h:
        if default is None:
            raise FormatError(f"mandatory header key '{key}' is missing", hp)
        return default
    val = h[key]
    try:
        if isinstance(val, list):
            raise ValueError
        out = int(str(val).strip())
    except ValueError:
        raise FormatError(f"header key '{key}' = {val!r} is not an integer", hp) from None
    if out < minimum:
        raise FormatError(f"header key '{key}' = {out} must be ≥ {minimum}", hp)
    return out


def read_envi_header(path: str | Path) -> EnviHeader:
    """Parse and check an ENVI header and locate its data file (no data read).

    Parameters
    ----------
    path
        The ``.hdr`` file or the data file.

    Raises
    ------
    InputError
        The path does not exist or is a folder.
    FormatError
        Unparseable header, missing/invalid mandatory key, unknown data type,
        missing data file, or a data file whose size is not
        ``header offset + lines·samples·bands·itemsize``.
    """
    hp = find_header_file(path)
    h = read_header_pairs(hp, MANAGED_KEYS)
    if "spectral library" in str(h.get("file type", "")).lower():
        # spectra as lines, wavelengths along samples, one band: no cube, and its data
        # file (.sli) is no cube data file — say so instead of a missing-file error
        raise FormatError(f"an ENVI spectral library ({h.get('lines', '?')} spectra of "
                          f"{h.get('samples', '?')} wavelengths), not an image cube; "
                          "use it as a reference spectrum (mehs.calibration.spectra."
                          "load_spectrum)", hp)
    samples = _int_field(h, "samples", hp)
    lines = _int_field(h, "lines", hp)
    bands = _int_field(h, "bands", hp)
    if "data type" not in h:
        raise FormatError("mandatory header key 'data type' is missing", hp)
    code = str(h["data type"]).strip()
    table = envi_dtypes()
    if code not in table:
        raise FormatError(f"unknown ENVI data type {code!r} (known: "
                          f"{', '.join(sorted(table, key=int))})", hp)
    dtype = table[code]
    if "interleave" in h:
        inter = str(h["interleave"]).strip().lower()
        if inter not in INTERLEAVES:
            raise FormatError(f"unknown interleave {h['interleave']!r} "
                              "(expected bil, bip or bsq)", hp)
    elif bands == 1:
        inter = "bsq"  # all interleaves coincide for one band
    else:
        raise FormatError("mandatory header key 'interleave' is missing", hp)
    if "byte order" in h:
        bo = _int_field(h, "byte order", hp, minimum=0)
        if bo not in (0, 1):
            raise FormatError(f"byte order must be 0 or 1, got {bo}", hp)
    else:
        bo = 0
        if dtype.itemsize > 1:
            warnings.warn(f"{hp}: no 'byte order' key; assuming 0 (little-endian)",
                          stacklevel=2)
    offset = _int_field(h, "header offset", hp, default=0, minimum=0)
    if _has_frame_offsets(h):
        raise FormatError("ENVI frame offsets are not supported", hp)
    dtype = dtype.newbyteorder("<" if bo == 0 else ">")
    given = Path(path)
    # a data file the caller named is the one read (several may share the header's stem)
    data_path = (given if given.suffix.lower() != ".hdr" and given.is_file()
                 else find_data_file(hp, inter))
    expected = offset + lines * samples * bands * dtype.itemsize
    actual = data_path.stat().st_size
    if actual != expected:
        what = "truncated" if actual < expected else "larger than its header says"
        raise FormatError(
            f"data file is {what}: expected {expected} bytes (header offset {offset} + "
            f"{lines} lines × {samples} samples × {bands} bands × {dtype.itemsize} bytes), "
            f"found {actual}", data_path)
    return EnviHeader(hp, data_path, lines, samples, bands, dtype, inter, bo, offset, h)


def _has_frame_offsets(h: dict) -> bool:
    for key in ("major frame offsets", "minor frame offsets"):
        val = h.get(key)
        if val is None:
            continue
        vals = val if isinstance(val, list) else [val]
        try:
            if any(int(v) != 0 for v in vals):
                return True
        except ValueError:
            return True
    return False


def _float_list(val: Any, key: str, n: int, hp: Path) -> np.ndarray:
    items = val if isinstance(val, list) else [v for v in re.split(r"[,\s]+", str(val)) if v]
    out = np.empty(len(items))
    for i, s in enumerate(items):
        try:
            out[i] = float(s)
        except ValueError:
            raise FormatError(f"'{key}' value {s!r} (band {i + 1}) is not a number",
                              hp) from None
    if out.size != n:
        raise FormatError(f"'{key}' has {out.size} values for {n} bands", hp)
    return out


_START_TIME_RE = re.compile(r"^(?:(UTC)\s*TIME\s*:)?\s*(\d{1,2}:\d{2}(?::\d{2}(?:\.\d+)?)?)$",
                            re.IGNORECASE)


def _with_start_time(iso_day: str, start: Any) -> str:
    """Add Specim's separate ``Start Time = UTC TIME: HH:MM:SS`` to a date-only value.

    Specim Lumo/IQ headers carry the day in ``acquisition date`` and the
    clock time in ``Start Time``; without it two captures of one day
    cannot be ordered.
    """
    if not isinstance(start, str):
        return iso_day
    m = _START_TIME_RE.match(start.strip())
    if not m:
        return iso_day
    return parse_acquisition_date(f"{iso_day} {m.group(2)}{'Z' if m.group(1) else ''}") \
        or iso_day


def _cube_fields(hdr: EnviHeader) -> dict[str, Any]:
    """SpectralCube keyword arguments from the header's optional keys."""
    h, hp, nb = hdr.fields, hdr.header_path, hdr.bands
    if "wavelength" not in h:
        raise FormatError("header has no 'wavelength' list; mehs needs band centres", hp)
    wl = _float_list(h["wavelength"], "wavelength", nb, hp)
    unit = str(h.get("wavelength units", "")).strip().lower()
    scale = UNIT_SCALE.get(unit)
    if scale is None:
        if unit in ("unknown", "index", ""):
            said = repr(h["wavelength units"]) if "wavelength units" in h else "not given"
            if (unit != "index" and np.all(np.abs(wl) < MAX_MICROMETRES)
                    and not np.all(wl == np.round(wl))):
                # ENVI Classic files (AVIRIS, spectral libraries) list band centres in µm;
                # without units they are not nm: 0.4–2.5 nm would be X-rays. (Whole
                # numbers are band indices, not µm: those keep the old reading.)
                scale = 1e3
                warnings.warn(f"{hp}: wavelength units {said}; band centres "
                              f"{wl.min():g}..{wl.max():g} read as micrometres", stacklevel=3)
            else:
                scale = 1.0
                if "wavelength units" in h:
                    warnings.warn(f"{hp}: wavelength units {said}; assuming nanometres",
                                  stacklevel=3)
        else:
            raise FormatError(f"wavelength units {h['wavelength units']!r} are not a "
                              "length mehs converts (Nanometers, Micrometers, Millimeters, "
                              "Centimeters, Meters, Angstroms); wavenumbers and "
                              "frequencies are refused", hp)
    try:
        wl = validate_wavelengths(wl * scale, nb, hp)
    except InputError as exc:
        raise FormatError(f"'wavelength': {exc.problem}", hp) from None
    why = units_mismatch(wl, scale, unit, h.get("wavelength units", ""))
    if why:
        raise FormatError(why, hp)
    kw: dict[str, Any] = {"wavelengths": wl}
    if "fwhm" in h:
        fw = _float_list(h["fwhm"], "fwhm", nb, hp) * scale
        if not np.all(np.isfinite(fw) & (fw > 0)):
            raise FormatError("'fwhm' values must be finite and positive", hp)
        kw["fwhm"] = fw
    if "tint" in h:
        try:
            t = float(str(h["tint"]).strip())
        except ValueError:
            raise FormatError(f"'tint' = {h['tint']!r} is not a number (ms)", hp) from None
        if not (np.isfinite(t) and t > 0):
            raise FormatError(f"'tint' = {t} ms must be positive", hp)
        kw["integration_time_ms"] = t
    if "acquisition date" in h:
        raw = h["acquisition date"]
        raw = ", ".join(raw) if isinstance(raw, list) else str(raw)
        iso = parse_acquisition_date(raw)
        if iso is not None and "T" not in iso:
            iso = _with_start_time(iso, h.get("start time"))
        if iso is None:
            warnings.warn(f"{hp}: acquisition date {raw!r} not understood; kept as text",
                          stacklevel=3)
            kw["acquisition_date"] = raw
        else:
            kw["acquisition_date"] = iso
    if "default bands" in h:
        try:
            db = [int(float(v)) - 1 for v in
                  (h["default bands"] if isinstance(h["default bands"], list)
                   else [h["default bands"]])]
        except ValueError:
            db = []
        if len(db) == 3 and all(0 <= b < nb for b in db):
            kw["default_bands"] = tuple(db)
        elif len(db) != 1:  # a single grey band is legal ENVI but not an RGB triple
            warnings.warn(f"{hp}: default bands {h['default bands']!r} ignored "
                          f"(need three 1-based indices in 1..{nb})", stacklevel=3)
    if "binning" in h:
        vals = h["binning"] if isinstance(h["binning"], list) else [h["binning"]]
        try:
            b = tuple(int(float(v)) for v in vals)
            if len(b) == 2 and min(b) >= 1:
                kw["binning"] = b
        except ValueError:
            pass
        if "binning" not in kw:
            warnings.warn(f"{hp}: binning {h['binning']!r} ignored", stacklevel=3)
    if "dark subtracted" in h:
        kw["dark_subtracted"] = str(h["dark subtracted"]).strip().lower() in (
            "1", "true", "yes")
    return kw


def read_envi(path: str | Path, *, memmap: bool = True) -> SpectralCube:
    """Read an ENVI cube as a :class:`SpectralCube` ``(lines, samples, bands)``.

    Parameters
    ----------
    path
        The ``.hdr`` file or the data file next to it.
    memmap
        If true (default) ``data`` is a read-only memmap view (no data read
        yet) — except when the file is big-endian or has a ``reflectance scale
        factor``: then the values are converted (native byte order, float32
        divided by the factor) into an in-memory array. If false, ``data`` is
        always an in-memory C-contiguous array.

    Returns
    -------
    SpectralCube
        ``data`` has the file's data type (native byte order), or float32 when
        a reflectance scale factor was applied (recorded in
        ``metadata["reflectance scale factor"]``, ``units="reflectance"``).
        Unsorted wavelengths are sorted together with the bands (a warning;
        the data is then copied).

    Raises
    ------
    InputError, FormatError
        See :func:`read_envi_header`; also a missing/invalid ``wavelength``
        list, FWHM count, non-numeric ``tint``.
    """
    hdr = read_envi_header(path)
    kw = _cube_fields(hdr)
    h, hp = hdr.fields, hdr.header_path
    data = hdr.open_memmap()
    why = byte_order_suspicion(data)  # a mislabelled byte order reads without any error
    if why:
        warnings.warn(f"{hp}: {byte_order_message(why, hdr.byte_order)}", ByteOrderWarning,
                      stacklevel=2)
    sf = reflectance_scale(h, hp)
    if sf is not None and sf != 1.0:
        out = np.empty(hdr.shape, np.float32)
        np.divide(data, np.float32(sf), out=out, casting="unsafe")
        data = out
    elif not data.dtype.isnative:
        data = data.astype(data.dtype.newbyteorder("="), order="C")
    elif not memmap:
        data = np.array(data, order="C")
    if sf is not None:
        kw["units"] = "reflectance"
    if str(h.get("data units", "")).strip():      # an empty value states nothing
        kw["units"] = str(h["data units"]).strip()
    elif sf is None:
        kw["units"] = "DN" if data.dtype.kind in "iu" else "unknown"
    meta = {k: v for k, v in h.items() if k not in MANAGED_KEYS}
    if sf is not None:
        meta["reflectance scale factor"] = sf
        if sf != 1.0 and "data ignore value" in meta:
            # The ignore value is in stored units (Specim Fenix uint16 reflectance:
            # 'reflectance scale factor = 65535', 'data ignore value = 0'). The data
            # are scaled now, so is the marker — else a written-back header would
            # flag values that no longer occur and miss the ones that do.
            try:
                raw_ignore = np.float32(float(str(meta["data ignore value"]).strip()))
            except ValueError:
                pass
            else:
                meta["data ignore value"] = float(raw_ignore / np.float32(sf))
    return SpectralCube(data=data, source=hp, metadata=meta, **kw)


# --------------------------------------------------------------------- writing
