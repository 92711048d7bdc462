"""Figures and conversions of a scene's 31-band cube (split from :mod:`mehs.dataset.scene_build`).

:func:`to_31_bands` resamples a cube to the dataset's bands, :func:`half_float_scale` picks the
power of two that fits the pseudo-HDR-RGB into half floats, :func:`dynamic_range_stops` is the
dataset's dynamic-range figure.
"""

from __future__ import annotations


def half_float_scale(peak: float) -> float:
    """``2**-k`` (k ≥ 0 smallest) so that ``peak · 2**-k`` fits half floats (≤ 65504).

    Fused radiance is in DN/ms and light sources exceed the half-float range of
    the pseudo-HDR-RGB EXR; the HS cube and its RGB images are then stored
    scaled by the same power of two (exact in floating point), recorded as
    ``quality.radiance_scale`` and in both file headers.
    """
    import math

    from mehs.io.exr import HALF_MAX

    if not (peak > HALF_MAX) or not math.isfinite(peak):
        return 1.0
    return 2.0 ** -math.ceil(math.log2(peak / HALF_MAX))


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

    from mehs.rgb import luminance

    Y = luminance(rgb)
    counted = np.ones(Y.shape, bool) if mask is None else np.asarray(mask) == 0
    ok = counted & (Y > 0)
    vals = Y[ok]
    if vals.size < 2:
        return None
    lo, hi = np.percentile(vals, [0.1, 99.9])
    if signed_luminance is not None:
        ys = np.asarray(signed_luminance, dtype=np.float64)
        if ys.shape != Y.shape:
            raise ValueError(f"signed luminance of shape {ys.shape} for an image of "
                             f"{Y.shape}")
        ys = ys[counted & np.isfinite(ys)]
        if ys.size:
            lo = max(float(lo), -float(np.percentile(ys, 0.1)))
    # an image all noise: its top percentile may sit below the floor, no range at all
    return max(0.0, float(np.log2(hi / lo))) if lo > 0 else None
