"""Per-band metadata that must follow its bands: reordered, checked, or rebuilt on resampling.

ENVI headers carry lists with one value per band besides ``wavelength`` and
``fwhm`` (which :class:`mehs.cube.SpectralCube` holds as arrays): the bad-band
list ``bbl``, ``band names``, and the per-band gains and offsets. When a cube's
unsorted wavelengths are sorted, these lists must be permuted with the bands,
or a flag on one band is written back on another; when the band set changes
(resampling), lists of the old length must not be written with the new bands.

All functions return new dicts; metadata values are the header's items (strings)
or numbers, kept as they are.

References
----------
ENVI header format, "bbl", "band names", "data gain values", "data offset values",
"data reflectance gain values", "data reflectance offset values", "solar irradiance" —
NV5 Geospatial,
*ENVI Header Files* (docs.nv5geospatialsoftware.com).
"""

from __future__ import annotations

import warnings
from typing import Any, Mapping

import numpy as np

#: Header keys holding exactly one value per band (other than wavelength and fwhm);
#: ``solar irradiance`` (W m⁻² µm⁻¹ per band) is what ENVI's radiometric calibration writes.
PER_BAND_KEYS = frozenset({"bbl", "band names", "data gain values", "data offset values",
                           "data reflectance gain values", "data reflectance offset values",
                           "solar irradiance"})

#: A resampled band is flagged bad when more than this share of its window's weight
#: lies on source bands flagged bad (its value then rests on a minority of the window).
BAD_WEIGHT_SHARE = 0.5


class BandMetadataWarning(UserWarning):
    """Per-band metadata whose length does not match the band count was dropped."""


def _items(value: Any) -> list | None:
    if isinstance(value, np.ndarray):
        value = value.tolist()
    return list(value) if isinstance(value, (list, tuple)) else None


def permute_band_metadata(meta: Mapping[str, Any], order: np.ndarray) -> dict[str, Any]:
    """``meta`` with each per-band list reordered as ``new[i] = old[order[i]]``.

    Parameters
    ----------
    meta
        Metadata dict (header keys, lower case).
    order
        int ``(bands,)`` permutation applied to the bands (e.g. ``argsort(wavelengths)``).
    """
    order = np.asarray(order, dtype=np.intp)
    out = dict(meta)
    for key in PER_BAND_KEYS & out.keys():
        items = _items(out[key])
        if items is not None and len(items) == order.size:
            out[key] = [items[i] for i in order]
    return out


def check_band_metadata(meta: Mapping[str, Any], n_bands: int,
                        source: Any = None) -> dict[str, Any]:
    """``meta`` without per-band lists whose length is not ``n_bands`` (with a warning).

    A header whose ``bbl`` has another length than ``bands`` cannot say which band a
    flag belongs to; keeping it would attach flags to the wrong bands on writing.
    """
    out = dict(meta)
    for key in sorted(PER_BAND_KEYS & out.keys()):
        items = _items(out[key])
        n = len(items) if items is not None else 1
        if n != n_bands:
            warnings.warn(f"{source or 'cube'}: {key!r} has {n} values for {n_bands} bands; "
                          "dropped", BandMetadataWarning, stacklevel=3)
            del out[key]
    return out


def bad_bands(meta: Mapping[str, Any], n_bands: int) -> np.ndarray | None:
    """bool ``(n_bands,)``: True where ``bbl`` flags a band bad (0); None without a usable bbl."""
    items = _items(meta.get("bbl"))
    if items is None or len(items) != n_bands:
        return None
    try:
        return np.asarray([float(str(v).strip()) == 0.0 for v in items], dtype=bool)
    except ValueError:
        return None


def resampled_band_metadata(meta: Mapping[str, Any], matrix: np.ndarray,
                            used: np.ndarray | None = None) -> dict[str, Any]:
    """Per-band metadata for bands made as ``dst = used @ src``.

    Names, gains and offsets describe the source bands and are dropped; a ``bbl``
    is recomputed. The bad bands are left out of ``used`` wherever good bands reach
    a target (ENVI: bad bands take no part in processing), so a target is bad (0)
    only when ``used`` still draws on a bad band (no good band reaches it) or when
    more than :data:`BAD_WEIGHT_SHARE` of its weight in ``matrix`` (all bands) lies
    on bad bands.

    Parameters
    ----------
    matrix
        ``(n_dst, n_src)`` resampling matrix over all source bands.
    used
        ``(n_dst, n_src)`` matrix actually applied (default ``matrix``).
    """
    matrix = np.abs(np.asarray(matrix, dtype=np.float64))
    used = matrix if used is None else np.abs(np.asarray(used, dtype=np.float64))
    bad = bad_bands(meta, matrix.shape[1])
    out = {k: v for k, v in meta.items() if k not in PER_BAND_KEYS}
    if bad is not None:
        total = matrix.sum(axis=1)
        share = matrix[:, bad].sum(axis=1) / np.where(total > 0, total, 1.0)
        from_bad = (used[:, bad] > 0).any(axis=1)
        out["bbl"] = [0 if (s > BAD_WEIGHT_SHARE or b) else 1 for s, b in zip(share, from_bad)]
    return out


#: Band centres that differ by more than this (nm) are another band set.
SAME_BAND_TOLERANCE_NM = 0.05


def check_same_bands(mine, theirs, me: str, them: str, source: Any = None) -> None:
    """Raise :class:`~mehs.errors.InputError` unless ``theirs`` are ``mine``'s band centres.

    For what was made for one band set (a calibration, a per-band response curve) and
    is applied to data of another with the same count (another binning offset or
    spectral calibration): each band would take another band's values. ``me`` and
    ``them`` name the two sides in the message.
    """
    from mehs.errors import InputError

    a = np.asarray(mine, dtype=np.float64).reshape(-1)
    b = np.asarray(theirs, dtype=np.float64).reshape(-1)
    if a.size != b.size:
        raise InputError(f"{me} has {a.size} bands, {them} {b.size}", source)
    d = np.abs(a - b)
    if d.size and d.max() > SAME_BAND_TOLERANCE_NM:
        k = int(np.argmax(d))
        raise InputError(f"{me} is for other wavelengths: band {k + 1} is {a[k]:.2f} nm there, "
                         f"{b[k]:.2f} nm in {them}", source)
