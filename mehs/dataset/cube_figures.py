"""Figures and conversions of a scene's 31-band cube (split from :mod:`mehs.dataset.scene_build`).

:func:`to_31_bands` resamples a cube to the dataset's bands, :func:`half_float_scale` picks the
power of two that fits the pseudo-HDR-RGB into half floats, :func:`dynamic_range_stops` is the
dataset's dynamic-range figure.
"""

from __future__ import annotations


#: Half float's smallest normal number, 2^-14: below it the relative precision (2^-11)
#: falls off linearly (subnormals), a value at 10^-6 keeps 4 significant bits.
HALF_MIN_NORMAL = 2.0 ** -14

#: Level the scene's low end is stored at, at least (when the peak allows it): 6 stops above
#: :data:`HALF_MIN_NORMAL`, so that a channel down to 1/64 of the low-end luminance (the
#: blue of a saturated yellow) still keeps half float's full precision.
HALF_LOW_END = HALF_MIN_NORMAL * 64.0


def half_float_scale(peak: float, low: float | None = None) -> float:
    """Power of two ``2**-k`` the pseudo-HDR-RGB (and its HS cube) is stored multiplied by.

    Fused radiance is in DN/ms (or W sr⁻¹ m⁻² nm⁻¹, or the input's units) and its range is
    the scene's, not half float's: light sources exceed 65504, and a dim scene (or a cube
    in absolute radiance) lies below half's smallest normal 2^-14, where precision drops:
    a ColorChecker at 10⁻⁵ of its light was stored with errors up to 32 %. So:

    - ``peak > 65504``: the smallest ``k ≥ 0`` with ``peak · 2**-k ≤ 65504``;
    - ``0 < low < HALF_LOW_END`` (2^-8): the smallest ``k < 0`` that lifts ``low`` to it,
      as far as the peak still fits (the peak wins: an overflow is no value at all);
    - otherwise 1, so scenes in range keep their values as they are.

    ``low``: the low end of the scene's positive luminance that must keep its precision
    (:func:`luminance_low_end`; None: the peak alone decides). The factor is exact in
    floating point, so HS and RGB stay paired; it is recorded as ``quality.radiance_scale``
    and in both file headers (stored = value × scale).
    """
    import math

    from mehs.io.exr import HALF_MAX

    if not (math.isfinite(peak) and peak > 0):
        return 1.0
    top = math.floor(math.log2(HALF_MAX / peak))      # largest exponent the peak allows
    k = 0
    if low is not None and math.isfinite(low) and 0 < low < HALF_LOW_END:
        k = math.ceil(math.log2(HALF_LOW_END / low))
    return 2.0 ** min(k, top)


def luminance_low_end(rgb, mask=None, *, signed_luminance=None) -> float | None:
    """Low end of the positive luminance: its 0.1th percentile over pixels with mask 0,
    raised to at least −P0.1 of ``signed_luminance`` (the noise floor of a cube that keeps
    its negative estimates: values below it are noise, their precision is no matter).

    The low end of :func:`dynamic_range_stops`; None without two positive pixels.
    """
    lo, _ = _luminance_ends(rgb, mask, signed_luminance)
    return lo


def _luminance_ends(rgb, mask, signed_luminance) -> tuple[float | None, float | None]:
    import numpy as np

    from mehs.rgb import luminance

    Y = luminance(rgb)
    counted = np.ones(Y.shape, bool) if mask is None else np.asarray(mask) == 0
    vals = Y[counted & (Y > 0)]
    if vals.size < 2:
        return None, None
    lo, hi = np.percentile(vals, [0.1, 99.9])
    if signed_luminance is not None:
        ys = np.asarray(signed_luminance, dtype=np.float64)
        if ys.shape != Y.shape:
            raise ValueError(f"signed luminance of shape {ys.shape} for an image of "
                             f"{Y.shape}")
        ys = ys[counted & np.isfinite(ys)]
        if ys.size:
            lo = max(float(lo), -float(np.percentile(ys, 0.1)))
    return float(lo), float(hi)


def to_31_bands(cube, *, method: str = "gaussian", fwhm: float = 10.0):
    """The cube on the 31 bands 400..700 nm (unchanged if already on them)."""
    import numpy as np

    from mehs.rgb import WAVELENGTHS_31

    if cube.bands == 31 and np.allclose(cube.wavelengths, WAVELENGTHS_31, atol=1e-6):
        return cube
    from mehs.synthesis.resample import resample_cube

    return resample_cube(cube, WAVELENGTHS_31, method=method, fwhm=fwhm)


def dynamic_range_stops(rgb, mask=None, *, signed_luminance=None) -> float | None:
    """log2 of the ratio between the 99.9th and 0.1th percentile of positive luminance.

    Percentiles instead of max/min keep single hot or dead pixels from deciding it.

    ``signed_luminance`` ``(H, W)``: Y of the cube before the RGB step clips negatives
    (a fused cube keeps its signed estimates, noise around zero radiance). Its
    negative tail mirrors the noise: the low end is then at least ``−P0.1`` of it,
    the level noise alone reaches as often as the low percentile itself. Without
    that floor the 0.1th percentile of positive Y fell among noise samples arbitrarily
    close to 0: a colorchecker at 10⁻⁴ of normal light, 14.8 stops in the simulator's
    radiance, read 18.4 stops (10⁻⁵, almost all noise: 15.2 stops, passing the rule);
    with the floor 8.7 and 5.3, as the cube clipped in the merge reads (9.4, 6.2).
    A cube with no negative luminance gives the same figure as without it.
    """
    import numpy as np

    lo, hi = _luminance_ends(rgb, mask, signed_luminance)
    if lo is None:
        return None
    return max(0.0, float(np.log2(hi / lo))) if lo > 0 else None
