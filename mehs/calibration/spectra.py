"""Reference spectra for radiometric calibration: files, colour-science names, band averages.

A reference spectrum (a panel's reflectance, an illuminant's relative SPD, a
calibrated lamp's or integrating sphere's spectral radiance) arrives as

- a CSV/text table: wavelength (nm) in the first column, value in the second,
  an optional third column with the value's relative standard uncertainty;
  ``#`` comments, one header line and ``,``/``;``/tab/space separators are
  accepted (the layouts calibration certificates and spectrometer exports use);
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


def _rows_from_text(path: Path) -> list[list[float]]:
    text = path.read_text(encoding="utf-8-sig", errors="strict")
    rows: list[list[float]] = []
    header_seen = False
    sample = "\n".join(ln for ln in text.splitlines()[:20] if ln.strip() and not ln.lstrip().startswith("#"))
    try:
        dialect = csv.Sniffer().sniff(sample, delimiters=",;\t ")
        delim = dialect.delimiter
    except csv.Error:
        delim = ","
    for n, line in enumerate(text.splitlines(), 1):
        s = line.split("#", 1)[0].strip()
        if not s:
            continue
        parts = [p for p in (s.split(delim) if delim != " " else s.split()) if p.strip() != ""]
        try:
            rows.append([float(p) for p in parts])
        except ValueError:
            if rows or header_seen:
                raise FormatError(f"line {n} is not numbers: {line.strip()!r}", path) from None
            header_seen = True
    return rows


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

        cube = read_envi(p if p.suffix.lower() == ".hdr" else p.with_suffix(".hdr"))
        data = np.asarray(cube.data, dtype=np.float64)
        vals = data.reshape(-1, data.shape[-1]).mean(axis=0)
        wl, vals = np.asarray(cube.wavelengths, dtype=np.float64), vals
        unc = None
    else:
        try:
            rows = _rows_from_text(p)
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
    return Spectrum(wl, vals, str(p), unc)


def band_average(spectrum: Spectrum, centres: np.ndarray, fwhm: np.ndarray | float | None, *,
                 what: str = "spectrum", partial: bool = False) -> np.ndarray:
    """float64 ``(bands,)``: the spectrum seen by Gaussian bands of ``centres`` and ``fwhm`` (nm).

    Every band's ±1 FWHM window must lie inside the table (no extrapolation: a
    panel file ending at 780 nm cannot calibrate a 1000 nm band); otherwise an
    :class:`InputError` names the first uncovered band — or, with ``partial``,
    uncovered bands are NaN. Without ``fwhm`` the table is interpolated at the centres.
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
    if fw is None:
        return np.where(bad, np.nan, np.interp(c, wl, v))
    step = min(0.5, float(np.min(np.diff(wl))) / 2)
    out = np.full_like(c, np.nan)
    for i, (ci, fi) in enumerate(zip(c, fw)):
        if bad[i]:
            continue
        sig = fi / (2 * np.sqrt(2 * np.log(2)))
        x = np.arange(max(wl[0], ci - 3 * sig), min(wl[-1], ci + 3 * sig) + step, step)
        w = np.exp(-0.5 * ((x - ci) / sig) ** 2)
        out[i] = float(np.sum(w * np.interp(x, wl, v)) / np.sum(w))
    return out
