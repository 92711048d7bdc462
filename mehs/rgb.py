"""Spectra → CIE XYZ → linear sRGB, as in the paper's pseudo-HDR-RGB (§3.1).

The XYZ scale constant is ``k = 1 / Σ_i ȳ(λ_i)`` over the cube's own band
centres, so a flat spectrum of value 1 has ``Y = 1`` whatever the band set.
:func:`spectra_to_XYZ` is the one XYZ function of the toolkit: the pseudo-RGB
images and the SSR luminance restoration both use it, so their ``X+Y+Z`` agree.

References
----------
- CIE 015:2018 Colorimetry, 4th edition (CIE 1931 2° standard observer).
- IEC 61966-2-1:1999 sRGB (the matrix below, D65 white).
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np

from mehs.errors import InputError

CMFS_NAME = "CIE 1931 2 Degree Standard Observer"

#: XYZ → linear sRGB (D65), the matrix printed in the paper and IEC 61966-2-1.
XYZ_TO_SRGB = np.array([[3.2406, -1.5372, -0.4986],
                        [-0.9689, 1.8758, 0.0415],
                        [0.0557, -0.2040, 1.0507]])

#: The 31 target bands of the ME HS set: 400, 410, …, 700 nm.
WAVELENGTHS_31 = np.arange(400.0, 701.0, 10.0)


@lru_cache(maxsize=32)
def _cmfs_at(wl_key: tuple[float, ...]) -> np.ndarray:
    import colour

    cmfs = colour.MSDS_CMFS[CMFS_NAME]
    wl = np.asarray(wl_key)
    lo, hi = cmfs.wavelengths[0], cmfs.wavelengths[-1]
    if wl.min() < lo or wl.max() > hi:
        raise InputError(
            f"wavelengths {wl.min():.1f}..{wl.max():.1f} nm fall outside the "
            f"CIE 1931 2° tables ({lo:.0f}..{hi:.0f} nm)")
    # The tables are at 1 nm, so integer band centres are read exactly.
    out = np.stack([np.interp(wl, cmfs.wavelengths, cmfs.values[:, c])
                    for c in range(3)], axis=1)
    out.setflags(write=False)
    return out


def cmfs_matrix(wavelengths: np.ndarray) -> np.ndarray:
    """Scaled colour-matching matrix ``M`` of shape ``(bands, 3)`` so that ``XYZ = S @ M``.

    ``M = k · [x̄ ȳ z̄](λ)`` with ``k = 1 / Σ ȳ(λ_i)``.
    """
    wl = np.asarray(wavelengths, dtype=np.float64).reshape(-1)
    cmf = _cmfs_at(tuple(wl.tolist()))
    return cmf / cmf[:, 1].sum()


def spectra_to_XYZ(spectra: np.ndarray, wavelengths: np.ndarray) -> np.ndarray:
    """CIE XYZ of spectra.

    Parameters
    ----------
    spectra
        Array of shape ``(..., bands)``.
    wavelengths
        Band centres in nm, shape ``(bands,)``.

    Returns
    -------
    ndarray
        Shape ``(..., 3)``, float32 for float32 input, float64 otherwise.
    """
    spectra = np.asarray(spectra)
    wl = np.asarray(wavelengths, dtype=np.float64).reshape(-1)
    if spectra.shape[-1] != wl.size:
        raise InputError(
            f"spectra have {spectra.shape[-1]} bands but {wl.size} wavelengths were given")
    dtype = np.float32 if spectra.dtype == np.float32 else np.float64
    return spectra.astype(dtype, copy=False) @ cmfs_matrix(wl).astype(dtype)


def XYZ_to_linear_sRGB(XYZ: np.ndarray, clip_negative: bool = True) -> np.ndarray:
    """Linear sRGB from XYZ with the paper's matrix; negatives clipped to 0 by default."""
    XYZ = np.asarray(XYZ)
    dtype = np.float32 if XYZ.dtype == np.float32 else np.float64
    rgb = XYZ @ XYZ_TO_SRGB.T.astype(dtype)
    if clip_negative:
        np.maximum(rgb, 0, out=rgb)
    return rgb


def spectra_to_linear_sRGB(spectra: np.ndarray, wavelengths: np.ndarray,
                           clip_negative: bool = True) -> np.ndarray:
    """Pseudo-HDR-RGB: spectra ``(..., bands)`` → linear sRGB ``(..., 3)``, unnormalised."""
    return XYZ_to_linear_sRGB(spectra_to_XYZ(spectra, wavelengths), clip_negative)


def linear_sRGB_to_XYZ(rgb: np.ndarray) -> np.ndarray:
    """Inverse of the paper's matrix: linear sRGB ``(..., 3)`` → XYZ ``(..., 3)``."""
    rgb = np.asarray(rgb)
    dtype = np.float32 if rgb.dtype == np.float32 else np.float64
    return rgb @ np.linalg.inv(XYZ_TO_SRGB).T.astype(dtype)
