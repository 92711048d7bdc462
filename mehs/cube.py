"""The spectral cube type shared by every stage.

A :class:`SpectralCube` holds data in native ENVI orientation
``(lines, samples, bands)`` — never rotated implicitly — together with the
band centres (nm), optional FWHMs (nm), units and the acquisition metadata that
later stages need (integration time, date, binning, dark subtraction, source).
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from mehs.bandmeta import check_band_metadata, permute_band_metadata
from mehs.errors import InputError


class UnsortedWavelengthsWarning(UserWarning):
    """Wavelengths were not ascending; bands were reordered together with the data."""


def validate_wavelengths(wavelengths: Any, n_bands: int | None = None,
                         source: str | Path | None = None) -> np.ndarray:
    """Return ``wavelengths`` as a float64 vector after checking it.

    Wavelengths must be numeric, finite, positive and unique, and (when
    ``n_bands`` is given) as many as the bands. Order is *not* checked here.

    Raises
    ------
    InputError
        Naming ``source`` and the problem.
    """
    try:
        wl = np.asarray(wavelengths, dtype=np.float64).reshape(-1)
    except (TypeError, ValueError) as exc:
        raise InputError(f"wavelengths are not numeric ({exc})", source) from None
    if n_bands is not None and wl.size != n_bands:
        raise InputError(
            f"{wl.size} wavelengths given for {n_bands} bands", source)
    if wl.size == 0:
        raise InputError("no wavelengths given", source)
    if not np.all(np.isfinite(wl)):
        bad = np.flatnonzero(~np.isfinite(wl))[:5].tolist()
        raise InputError(f"wavelengths are not finite at band index {bad}", source)
    if np.any(wl <= 0):
        raise InputError("wavelengths must be positive (nm)", source)
    uniq, counts = np.unique(wl, return_counts=True)
    if np.any(counts > 1):
        raise InputError(
            f"duplicate wavelengths {uniq[counts > 1][:5].tolist()} nm", source)
    return wl


@dataclass
class SpectralCube:
    """A hyperspectral cube with its band set and acquisition metadata.

    Attributes
    ----------
    data
        Array or ``numpy.memmap`` of shape ``(lines, samples, bands)``.
    wavelengths
        Band centres in nm, shape ``(bands,)``, ascending after construction.
    fwhm
        Band widths (full width at half maximum) in nm, shape ``(bands,)``, or
        ``None`` when unknown.
    units
        ``"DN"`` for raw counts, ``"relative radiance"``, ``"reflectance"``, …
    integration_time_ms
        Exposure (integration) time in milliseconds, or ``None``.
    acquisition_date
        ISO-8601 date/time string, or ``None``.
    binning
        ``(spectral, spatial)`` binning factors, or ``None``.
    dark_subtracted
        Whether a dark reference has been subtracted.
    source
        The file the cube was read from, if any.
    default_bands
        0-based indices of the bands to show as (R, G, B), or ``None``.
    metadata
        Any other header fields, kept so a read→write round trip loses nothing.
    """

    data: np.ndarray
    wavelengths: np.ndarray
    fwhm: np.ndarray | None = None
    units: str = "DN"
    integration_time_ms: float | None = None
    acquisition_date: str | None = None
    binning: tuple[int, int] | None = None
    dark_subtracted: bool = False
    source: Path | None = None
    default_bands: tuple[int, int, int] | None = None
    metadata: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        src = self.source
        if self.data.ndim != 3:
            raise InputError(
                f"a cube must be 3-D (lines, samples, bands), got shape {self.data.shape}",
                src)
        nb = self.data.shape[2]
        self.wavelengths = validate_wavelengths(self.wavelengths, nb, src)
        if self.fwhm is not None:
            fw = np.asarray(self.fwhm, dtype=np.float64).reshape(-1)
            if fw.size != nb:
                raise InputError(f"{fw.size} FWHM values given for {nb} bands", src)
            if not np.all(np.isfinite(fw) & (fw > 0)):
                raise InputError("FWHM values must be finite and positive", src)
            self.fwhm = fw
        if self.integration_time_ms is not None:
            t = float(self.integration_time_ms)
            if not (np.isfinite(t) and t > 0):
                raise InputError(f"integration time must be positive, got {t} ms", src)
            self.integration_time_ms = t
        if self.default_bands is not None:
            db = tuple(int(b) for b in self.default_bands)
            if any(b < 0 or b >= nb for b in db):
                raise InputError(f"default bands {db} outside 0..{nb - 1}", src)
            self.default_bands = db
        self.metadata = check_band_metadata(self.metadata or {}, nb, src)
        order = np.argsort(self.wavelengths, kind="stable")
        if np.any(order != np.arange(nb)):
            warnings.warn(
                f"{src or 'cube'}: wavelengths are not sorted; bands reordered "
                "together with the data", UnsortedWavelengthsWarning, stacklevel=3)
            if np.array_equal(order, np.arange(nb - 1, -1, -1)):
                # descending (a common spectrometer order): a reversed view, not a copy —
                # a memory-mapped scan stays on disk (a 5000-line FX10 exposure is 2.3 GB;
                # the copy read each exposure of a bracket whole into memory)
                self.data = self.data[:, :, ::-1]
            else:
                self.data = np.ascontiguousarray(np.asarray(self.data)[:, :, order])
            self.wavelengths = self.wavelengths[order]
            if self.fwhm is not None:
                self.fwhm = self.fwhm[order]
            self.metadata = permute_band_metadata(self.metadata, order)  # bbl, band names, …
            if self.default_bands is not None:
                inv = np.empty_like(order)
                inv[order] = np.arange(nb)
                self.default_bands = tuple(int(inv[b]) for b in self.default_bands)

    @property
    def shape(self) -> tuple[int, int, int]:
        return tuple(self.data.shape)  # type: ignore[return-value]

    @property
    def lines(self) -> int:
        return self.data.shape[0]

    @property
    def samples(self) -> int:
        return self.data.shape[1]

    @property
    def bands(self) -> int:
        return self.data.shape[2]

    def with_data(self, data: np.ndarray, **changes: Any) -> "SpectralCube":
        """A copy sharing this cube's metadata, with new ``data`` (and any field changes)."""
        return replace(self, data=data, **changes)

    def band_index(self, wavelength_nm: float) -> int:
        """Index of the band whose centre is nearest to ``wavelength_nm``."""
        return int(np.argmin(np.abs(self.wavelengths - wavelength_nm)))

    def __repr__(self) -> str:
        wl = self.wavelengths
        return (f"SpectralCube(shape={self.shape}, dtype={self.data.dtype}, "
                f"wavelengths={wl[0]:.2f}..{wl[-1]:.2f} nm, units={self.units!r}, "
                f"integration_time_ms={self.integration_time_ms}, source={self.source})")
