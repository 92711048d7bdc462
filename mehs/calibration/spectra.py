"""Reference spectra for radiometric calibration: files, colour-science names, band averages.

A reference spectrum (a panel's reflectance, an illuminant's relative SPD, a
calibrated lamp's or integrating sphere's spectral radiance) arrives as

- a CSV/text table: wavelength (nm) in the first column, value in the second,
  an optional third column with the value's relative standard uncertainty;
  ``#`` comments, header lines before the numbers, ``,``/``;``/tab/space separators
  and decimal commas with ``;``/tab separators (``400;0,95``) are accepted (the layouts
  calibration certificates and spectrometer exports use);
- an ENVI file (a spectral library ``.sli``/``.hdr`` with one spectrum, or a
  cube whose pixels are averaged), read by :func:`mehs.io.envi.read_envi`;
- a colour-science illuminant name (``D65``, ``A``, ``HP1``, ``FL2``, ``LED-B3``, …).

:func:`band_average` turns a finely tabulated spectrum into the value each
camera band sees: the table integrated against the band's Gaussian spectral
response (its FWHM from the capture header) — not the value at the band
centre, which misreads line spectra (fluorescent, sodium) by far more than a
band's width.
"""

from __future__ import annotations

import csv
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from mehs.errors import FormatError, InputError


@dataclass(frozen=True)
class Spectrum:
    """A tabulated spectrum: ``wavelengths`` (nm, ascending), ``values``, optional relative ``uncertainty``."""

    wavelengths: np.ndarray
    values: np.ndarray
    source: str
    uncertainty: np.ndarray | None = None
    #: the text file's header lines and comments (a certificate's unit is read from them)
    header: str = ""


#: a number written with a decimal comma (European spectrometer exports: ``0,95``)
_DECIMAL_COMMA = re.compile(r"^[+-]?\d*,\d+(?:[eE][+-]?\d+)?$")


def _delimiter(data_lines: list[str]) -> str:
    """The column separator of the table's data lines (``" "``: runs of blanks)."""
    # ';' or a tab on every data line is the separator: the sniffer prefers ',' there,
    # which in "400;0,95" (decimal comma, the European CSV convention) is the decimal mark
    for d in (";", "\t"):
        if data_lines and all(d in ln for ln in data_lines):
            return d
    sample = "\n".join(data_lines)
    try:
        return csv.Sniffer().sniff(sample, delimiters=",;\t ").delimiter
    except csv.Error:
        # columns aligned by runs of spaces/tabs (spectrometer exports) defeat the sniffer
        return "," if ("," in sample or ";" in sample) else " "


def _rows_from_text(path: Path) -> tuple[list[list[float]], str]:
    """Rows of numbers of a text table, and its header text.

    Any lines before the first row of numbers are the header (a title, column names, a
    certificate's unit line — also a title that starts with a digit, "1000 W QTH lamp"),
    and every ``#`` comment belongs to it too; returned joined by newlines (a
    certificate's unit is read from it, :mod:`mehs.calibration.units`).
    """
    text = path.read_text(encoding="utf-8-sig", errors="strict")
    lines = [ln.partition("#") for ln in text.splitlines()]
    comments = [c.strip() for _, _, c in lines if c.strip()]
    body = [(n, b.strip()) for n, (b, _, _) in enumerate(lines, 1) if b.strip()]
    # the separator is sniffed on the data lines only: a certificate's title and column
    # names ("Wavelength (nm); Radiance (W/(m2 sr nm))") mislead the sniffer
    data_lines = [s for _, s in body if s[0].isdigit() or s[0] in "+-.,"][:20]
    delim = _delimiter(data_lines)
    rows: list[list[float]] = []
    header: list[str] = []
    for n, s in body:
        parts = [p.strip() for p in (s.split(delim) if delim != " " else s.split())]
        parts = [p for p in parts if p]
        if delim != ",":
            parts = [p.replace(",", ".") if _DECIMAL_COMMA.match(p) else p for p in parts]
        try:
            rows.append([float(p) for p in parts])
        except ValueError:
            if rows:
                raise FormatError(f"line {n} is not numbers: {s!r} (columns separated by "
                                  f"{'blanks' if delim == ' ' else repr(delim)})", path) from None
            header.append(s)   # a header line (title, column names, certificate number)
    return rows, "\n".join(header + comments)


def _read_library(hdr: Path, given: Path, what: str) -> tuple[np.ndarray, np.ndarray] | None:
    """(wavelengths nm, values) of a one-spectrum ENVI spectral library, or None for another ENVI file.

    A library is laid out across the header's samples (``lines`` spectra of
    ``samples`` wavelengths, ``bands = 1``), not as an image cube.
    """
    import spectral.io.envi as envi

    try:
        h = envi.read_envi_header(str(hdr))
    except Exception:       # noqa: BLE001 - read_envi gives the precise error
        return None
    if str(h.get("file type", "")).strip().lower() != "envi spectral library":
        return None
    data = given if given.suffix.lower() != ".hdr" else next(
        (q for q in (hdr.with_suffix(e) for e in (".sli", ".SLI", ".dat", ".img", "")) if q.is_file()),
        hdr.with_suffix(".sli"))
    try:
        lib = envi.open(str(hdr), str(data))
        wl = np.asarray(lib.bands.centers, dtype=np.float64)
        # SPy reads a library from byte 0 whatever its ``header offset`` (spectral 0.25
        # envi.open: np.fromfile without offset), so a library with an embedded header
        # came out shifted by that many bytes without any error; read the values here
        p = envi.gen_params(h)
        n = p.nrows * p.ncols
        need = p.offset + n * np.dtype(p.dtype).itemsize
        have = Path(data).stat().st_size
        if have < need:
            raise ValueError(f"data file holds {have} bytes, the header describes {need} "
                             f"(header offset {p.offset} + {p.nrows} × {p.ncols} values)")
        spectra = np.fromfile(data, dtype=p.dtype, count=n, offset=p.offset)
        spectra = spectra.astype(np.float64).reshape(p.nrows, p.ncols)
    except Exception as exc:  # noqa: BLE001 - SPy raises several kinds for a bad library
        raise FormatError(f"unreadable ENVI spectral library {what} ({exc})", hdr) from None
    if spectra.ndim != 2 or spectra.shape[0] != 1:
        names = h.get("spectra names") or []
        raise FormatError(f"{what} library holds {spectra.shape[0]} spectra "
                          f"({', '.join(map(str, names[:5]))}); give a file with one", hdr)
    if wl.size != spectra.shape[1]:
        raise FormatError(f"{what} library has {wl.size} wavelengths for {spectra.shape[1]} "
                          "values", hdr)
    unit = str(h.get("wavelength units", "nanometers")).strip().lower()
    if unit in ("micrometers", "micrometer", "microns", "micron", "um", "µm"):
        wl = wl * 1e3
    scale = h.get("reflectance scale factor")
    vals = spectra[0] / float(scale) if scale not in (None, "") else spectra[0]
    return wl, vals


def load_spectrum(spec: str | Path, *, what: str = "spectrum") -> Spectrum:
    """Read a reference spectrum (module docstring). ``what`` names it in errors."""
    p = Path(str(spec))
    if not p.exists():
        name = str(spec)
        import colour

        if name in colour.SDS_ILLUMINANTS:
            sd = colour.SDS_ILLUMINANTS[name]
            return Spectrum(np.asarray(sd.wavelengths, dtype=np.float64),
                            np.asarray(sd.values, dtype=np.float64),
                            f"colour.SDS_ILLUMINANTS[{name!r}]")
        raise InputError(f"{what} {name!r} is neither a file nor a colour-science illuminant "
                         "name (D65, A, HP1, FL2, LED-B3, ...)")
    if p.suffix.lower() in (".hdr", ".sli", ".img", ".dat"):
        from mehs.io.envi import read_envi

        hdr = p if p.suffix.lower() == ".hdr" else p.with_suffix(".hdr")
        lib = _read_library(hdr, p, what)
        if lib is not None:
            wl, vals = lib
        else:
            cube = read_envi(hdr)
            data = np.asarray(cube.data, dtype=np.float64)
            vals = data.reshape(-1, data.shape[-1]).mean(axis=0)
            wl, vals = np.asarray(cube.wavelengths, dtype=np.float64), vals
        unc = None
        header = ""
    else:
        try:
            rows, header = _rows_from_text(p)
        except UnicodeDecodeError:
            raise FormatError(f"{what} file is not text (CSV expected)", p) from None
        if len(rows) < 2:
            raise FormatError(f"{what} file holds fewer than 2 rows of numbers", p)
        widths = {len(r) for r in rows}
        if len(widths) != 1 or min(widths) < 2:
            raise FormatError(f"{what} file rows must all have 2 or 3 numbers "
                              "(wavelength nm, value[, relative uncertainty])", p)
        a = np.asarray(rows, dtype=np.float64)
        wl, vals = a[:, 0], a[:, 1]
        unc = a[:, 2] if a.shape[1] >= 3 else None
    if not (np.all(np.isfinite(wl)) and np.all(np.isfinite(vals))):
        raise FormatError(f"{what} holds NaN or inf", p)
    order = np.argsort(wl, kind="stable")
    wl, vals = wl[order], vals[order]
    if unc is not None:
        unc = unc[order]
    if np.any(np.diff(wl) <= 0):
        raise FormatError(f"{what} has repeated wavelengths", p)
    if wl[0] < 100 or wl[-1] > 20000:
        raise FormatError(f"{what} wavelengths {wl[0]:g}..{wl[-1]:g} do not look like nm", p)
    if np.any(vals < 0):
        raise FormatError(f"{what} has negative values (at {wl[vals < 0][0]:g} nm)", p)
    if unc is not None:
        bad = ~np.isfinite(unc) | (unc < 0) | (unc > 1)
        if bad.any():
            # certificates often print the uncertainty in per cent: 2.5 would become 250 %
            raise FormatError(f"{what}: the third column must be the relative standard "
                              "uncertainty as a fraction 0..1 (per cent / 100), got "
                              f"{unc[bad][0]:g} at {wl[bad][0]:g} nm", p)
    return Spectrum(wl, vals, str(p), unc, header)


#: a table with steps wider than this (nm) is a smooth source's certificate, not a lamp's lines
COARSE_STEP_NM = 10.0


#: a certificate tabulated at ≤ 10 nm is taken as smooth (spline) when spline and straight
#: line differ by less than this between its points: a QTH lamp or sphere at 10 nm steps
#: differs by 0.2 %, a discharge line by tens of per cent
SMOOTH_MIDPOINT_LIMIT = 0.02


def _log_spline(wl: np.ndarray, v: np.ndarray):
    from scipy.interpolate import CubicSpline

    if np.all(v > 0):
        cs = CubicSpline(wl, np.log(v))
        return lambda x: np.exp(cs(x))
    cs = CubicSpline(wl, v)
    return lambda x: np.maximum(cs(x), 0.0)


def _interpolant(wl: np.ndarray, v: np.ndarray, smooth: bool = False):
    """The spectrum between its tabulated points.

    Finely tabulated spectra (steps ≤ 10 nm: lamps with lines, measured panels, CIE
    illuminants) are interpolated linearly, which
    keeps a line's peak where it is. Calibration certificates of smooth sources are
    often coarse (NIST FEL lamps: 50–150 nm steps in the NIR), where a straight line
    under a Planck-like curve is 4–5 % low; those are interpolated as a cubic spline of
    ``ln L`` (L > 0; the values themselves otherwise), 0.04 % from Planck on the same
    points. ``smooth`` (a calibrated source's certificate): the spline also at ≤ 10 nm
    steps where the table has no lines (:data:`SMOOTH_MIDPOINT_LIMIT`) — a straight
    line between 10 nm points of a 3000 K lamp is 0.16 % low, the spline 4e-6 (as
    colour-science's Sprague interpolation, 6e-6).
    """
    if wl.size < 4:
        return lambda x: np.interp(x, wl, v)
    if float(np.max(np.diff(wl))) > COARSE_STEP_NM:
        return _log_spline(wl, v)
    if smooth and float(np.max(np.diff(wl))) > 1.0:
        f = _log_spline(wl, v)
        mid = 0.5 * (wl[1:] + wl[:-1])
        lin = np.interp(mid, wl, v)
        with np.errstate(invalid="ignore", divide="ignore"):
            dev = np.abs(f(mid) - lin) / np.maximum(np.abs(lin), 1e-300)
        if float(np.max(dev)) < SMOOTH_MIDPOINT_LIMIT:
            return f
    return lambda x: np.interp(x, wl, v)


#: Half-width of a band's Gaussian taken into its average, in σ. At ±3σ the 0.27 % of the
#: response beyond was dropped, and a discharge line 3–5σ from a band's centre with it
#: (FL2, HP1: 0.4–1 % off); beyond ±5σ lies 6e-7 of it.
GAUSS_SUPPORT_SIGMA = 5.0


def band_average(spectrum: Spectrum, centres: np.ndarray, fwhm: np.ndarray | float | None, *,
                 what: str = "spectrum", partial: bool = False, smooth: bool = False) -> np.ndarray:
    """float64 ``(bands,)``: the spectrum seen by Gaussian bands of ``centres`` and ``fwhm`` (nm).

    Every band's ±1 FWHM window must lie inside the table (no extrapolation: a
    panel file ending at 780 nm cannot calibrate a 1000 nm band); otherwise an
    :class:`InputError` names the first uncovered band — or, with ``partial``,
    uncovered bands are NaN. Without ``fwhm`` the table is interpolated at the centres.
    Between its points the table is linear, or a spline of ``ln L`` when coarse — or,
    with ``smooth`` (a calibrated source), wherever it has no lines (:func:`_interpolant`).
    """
    c = np.asarray(centres, dtype=np.float64).reshape(-1)
    wl, v = spectrum.wavelengths, spectrum.values
    fw = None if fwhm is None else np.broadcast_to(np.asarray(fwhm, dtype=np.float64), c.shape)
    half = np.zeros_like(c) if fw is None else fw
    bad = (c - half < wl[0] - 1e-9) | (c + half > wl[-1] + 1e-9)
    if bad.any() and not partial:
        k = int(np.flatnonzero(bad)[0])
        raise InputError(f"{what} ({spectrum.source}) covers {wl[0]:g}..{wl[-1]:g} nm, not band "
                         f"{k + 1} at {c[k]:.2f} nm (±{half[k]:g} nm) — {int(bad.sum())} of "
                         f"{c.size} bands uncovered; give a spectrum over the camera's range, or "
                         "calibrate the covered bands only (mehs calibrate --partial)")
    interp = _interpolant(wl, v, smooth)
    if fw is None:
        return np.where(bad, np.nan, interp(c))
    step = min(0.5, float(np.min(np.diff(wl))) / 2)
    out = np.full_like(c, np.nan)
    for i, (ci, fi) in enumerate(zip(c, fw)):
        if bad[i]:
            continue
        sig = fi / (2 * np.sqrt(2 * np.log(2)))
        lo = max(wl[0], ci - GAUSS_SUPPORT_SIGMA * sig)
        hi = min(wl[-1], ci + GAUSS_SUPPORT_SIGMA * sig)
        # the table's own nodes are on the grid, so the interpolated spectrum is linear
        # between grid points and the trapezoid rule does not smear a line's peak (a
        # plain sum over a 0.5 nm grid offset from the nodes erred by 0.7 % at FL11's lines)
        n = max(int(np.ceil((hi - lo) / min(step, sig / 20))), 1)
        x = np.union1d(np.linspace(lo, hi, n + 1), wl[(wl > lo) & (wl < hi)])
        w = np.exp(-0.5 * ((x - ci) / sig) ** 2)
        dx = np.diff(x)
        f = w * interp(x)
        out[i] = float(np.sum(dx * (f[1:] + f[:-1])) / np.sum(dx * (w[1:] + w[:-1])))
    return out
