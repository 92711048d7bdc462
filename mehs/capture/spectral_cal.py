"""Spectral calibration of a GenICam hyperspectral camera: band index → wavelength (nm)."""

from __future__ import annotations

from pathlib import Path
from typing import Sequence

import numpy as np

from mehs.errors import InputError


def read_calibration(path: str | Path) -> np.ndarray:
    """Band centres (nm) from a calibration file: one wavelength per band, whitespace/comma separated.

    Raises
    ------
    InputError
        Unreadable file, non-numbers, non-finite or non-increasing values.
    """
    p = Path(path)
    try:
        text = p.read_text()
    except OSError as exc:
        raise InputError(f"cannot read the wavelength calibration ({exc.strerror or exc})", p) from None
    try:
        wl = np.array([float(v) for v in text.replace(",", " ").split()], dtype=np.float64)
    except ValueError:
        raise InputError("wavelength calibration must hold numbers only (one per band, nm)", p) from None
    if wl.size < 2 or not np.all(np.isfinite(wl)) or np.any(np.diff(wl) <= 0):
        raise InputError(f"wavelength calibration must be ≥ 2 increasing finite numbers (nm), "
                         f"got {wl.size} values", p)
    if wl[0] < 100 or wl[-1] > 20000:
        # µm (0.4-1.0) would pass the checks above and be written into every capture header
        raise InputError(f"wavelength calibration {wl[0]:g}..{wl[-1]:g} does not look like nm "
                         "(micrometres? multiply by 1000)", p)
    return wl


def polynomial_wavelengths(coeffs: Sequence[float], bands: int, binning: int = 1,
                           offset: int = 0) -> np.ndarray:
    """λ = A·x² + B·x + C at the centre of each (binned) band; ``coeffs = (A, B, C)``.

    ``x`` is the unbinned sensor row: band ``b`` of a camera binning ``binning``
    rows starting at row ``offset`` covers rows ``offset + b·binning …`` and its
    centre is ``offset + b·binning + (binning − 1)/2``. Shape ``(bands,)``.

    References
    ----------
    Resonon, *Pika cameras: spectral calibration* (the ``A, B, C`` calibration
    coefficients shipped with every camera).
    """
    a, b, c = (float(v) for v in coeffs)
    x = int(offset) + np.arange(int(bands), dtype=np.float64) * int(binning) + (int(binning) - 1) / 2.0
    return (a * x + b) * x + c
