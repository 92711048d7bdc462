"""Luminance restoration (paper §3.3): give a predicted spectral shape the input's brightness.

An SSR model predicts a spectral *shape* ``S``; the HDR cube is

``HS = (X_rgb + Y_rgb + Z_rgb) / (X_S + Y_S + Z_S) · S``

where ``XYZ_rgb`` comes from the input linear sRGB (inverse of the paper's
matrix, :func:`mehs.rgb.linear_sRGB_to_XYZ`) and ``XYZ_S`` from the spectra with
the toolkit's one XYZ function :func:`mehs.rgb.spectra_to_XYZ` (k = 1/Σȳ), the
same that made the pseudo-HDR-RGB — so restoring the ground truth's own shape
gives back the ground truth.

Guard (no NaN, no inf): where ``X_S + Y_S + Z_S`` is not a positive finite number
(a zero, negative or non-finite predicted shape) ``S`` is replaced by a flat
spectrum, so the pixel still gets the input's ``X+Y+Z``. Where the rescaled
spectrum would overflow float32 the same flat fallback is used.
"""

from __future__ import annotations

import numpy as np

from mehs.errors import InputError
from mehs.rgb import XYZ_TO_SRGB, cmfs_matrix
from mehs.ssr.contract import all_finite


def _xyz_sum_vector(wavelengths: np.ndarray) -> np.ndarray:
    """``w`` with ``X+Y+Z = S @ w`` (the row sums of the scaled CMF matrix), ``(B,)`` float64."""
    return cmfs_matrix(np.asarray(wavelengths, dtype=np.float64)).sum(1)


def xyz_sum(spectra: np.ndarray, wavelengths: np.ndarray) -> np.ndarray:
    """``X + Y + Z`` of spectra ``(..., B)`` → ``(...)`` (float32 for float32 input)."""
    spectra = np.asarray(spectra)
    if spectra.shape[-1] != np.asarray(wavelengths).size:
        raise InputError(f"spectra have {spectra.shape[-1]} bands but "
                         f"{np.asarray(wavelengths).size} wavelengths were given")
    dtype = np.float32 if spectra.dtype == np.float32 else np.float64
    return spectra.astype(dtype, copy=False) @ _xyz_sum_vector(wavelengths).astype(dtype)


def rgb_xyz_sum(rgb: np.ndarray) -> np.ndarray:
    """``X + Y + Z`` of linear sRGB ``(..., 3)`` → ``(...)`` float64."""
    w = np.linalg.inv(XYZ_TO_SRGB).sum(0)
    return np.asarray(rgb, dtype=np.float64) @ w


def restore_luminance(S: np.ndarray, rgb: np.ndarray, wavelengths: np.ndarray, *,
                      return_fallback: bool = False, overwrite: bool = False):
    """Scale predicted spectra so each pixel has the input RGB's ``X+Y+Z``.

    Parameters
    ----------
    S
        Predicted spectra, shape ``(..., B)``.
    rgb
        The *unprocessed* linear sRGB input, shape ``(..., 3)`` (same leading shape).
    wavelengths
        Band centres of ``S`` in nm, shape ``(B,)``.

    return_fallback
        Also return the number of pixels that got the flat-spectrum fallback
        while the input has light (so a caller can report it; the evaluation
        always does); ``"mask"``: those pixels as a boolean array of the leading
        shape (so an evaluation can count them within its cropped, masked region).
    overwrite
        Write the result into ``S`` (when it is a writeable array of the output
        dtype) instead of a new array: for a caller that owns ``S``, such as a
        network's fresh output, it saves an image-sized allocation.

    Returns
    -------
    ndarray
        Shape ``(..., B)``, float32 for float32 ``S`` (float64 otherwise); always finite.
        With ``return_fallback``: ``(spectra, n_fallback)`` (or the mask for ``"mask"``).
    """
    S = np.asarray(S)
    rgb = np.asarray(rgb)
    if S.shape[:-1] != rgb.shape[:-1] or rgb.shape[-1] != 3:
        raise InputError(
            f"spectra of shape {S.shape} do not match RGB of shape {rgb.shape}")
    dtype = np.float32 if S.dtype == np.float32 else np.float64
    S = S.astype(dtype, copy=False)
    target = rgb_xyz_sum(rgb)
    with np.errstate(all="ignore"):
        have = xyz_sum(S, wavelengths).astype(np.float64)
        good = np.isfinite(have) & (have > 0) & np.isfinite(target)
        factor = np.where(good, target / np.where(good, have, 1.0), 0.0)
        f = factor.astype(dtype)[..., None]
        # (after a large network run the kernel may stall a fresh image-sized
        # allocation on memory compaction: 0.3 s became 4.6 s once, issue 16)
        out = np.multiply(S, f, out=S) if overwrite and S.flags.writeable else S * f
        if not all_finite(out):
            # A spectrum with mixed signs can have a tiny X+Y+Z and so a huge factor.
            good &= np.isfinite(out).all(-1)
    if not good.all():
        flat_sum = _xyz_sum_vector(wavelengths).sum()
        fill = (np.where(np.isfinite(target), target, 0.0) / flat_sum).astype(dtype)
        # (out is fresh, or the caller's to overwrite: filled where it is, not through
        # one more image-sized array)
        bad = ~good
        out[bad] = fill[bad][..., None]
    if return_fallback:
        # black input pixels (X+Y+Z = 0) come out black either way: not a substitution
        fell = ~good & (np.abs(np.nan_to_num(target)) > 0)
        return out, (fell if return_fallback == "mask" else int(np.count_nonzero(fell)))
    return out
