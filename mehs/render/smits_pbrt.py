"""RGB → spectrum for light sources as pbrt-v3 does it: Smits 1999 with the illuminant basis.

The paper's "PBRT renderer" row (Figs. 13–14) is pbrt-v3 compiled with ``SampledSpectrum``:
its image infinite light turns each environment-map RGB into a spectrum with
``SampledSpectrum::FromRGB(rgb, SpectrumType::Illuminant)`` — Smits' decomposition into
white + (cyan|magenta|yellow) + (red|green|blue), with the *illuminant* basis spectra
(``data/smits_illuminant_pbrt_v3.csv``), times 0.86445, negatives clamped to 0. pbrt averages
the basis over its 5 nm sample bins; here each output band is the average of the
piecewise-linear basis over ``[c − Δ/2, c + Δ/2]`` (Δ the band spacing) clipped to pbrt's
400–700 nm range. (:mod:`mehs.ssr.baselines`' ``smits`` uses Smits' *reflectance* basis, as
colour-science does; for lights pbrt uses this one.)

Shapes: ``rgb (..., 3)`` linear RGB → ``(..., B)`` float32 at ``wavelengths (B,)``.

References
----------
- Smits, B. (1999). An RGB-to-spectrum conversion for reflectances. JGT 4(4), 11–22.
- Pharr, M., Jakob, W. & Humphreys, G. (2016). Physically Based Rendering, 3rd ed., §5.2.2;
  pbrt-v3 ``src/core/spectrum.cpp``.
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np

from mehs.render.materials import DATA_DIR
from mehs.rgb import WAVELENGTHS_31

PBRT_ILLUMINANT_SCALE = 0.86445
PBRT_RANGE_NM = (400.0, 700.0)
BASIS_ORDER = ("white", "cyan", "magenta", "yellow", "red", "green", "blue")


@lru_cache(maxsize=None)
def _table() -> np.ndarray:
    rows = [ln for ln in (DATA_DIR / "smits_illuminant_pbrt_v3.csv").read_text("utf-8").splitlines()
            if ln and not ln.startswith(("#", "wavelength"))]
    return np.array([[float(x) for x in ln.split(",")] for ln in rows])


def _segment_average(lam: np.ndarray, vals: np.ndarray, lo: float, hi: float) -> float:
    """Mean of the piecewise-linear (lam, vals) over [lo, hi] (constant beyond the ends)."""
    x = np.unique(np.concatenate([[lo, hi], lam[(lam > lo) & (lam < hi)]]))
    y = np.interp(x, lam, vals)
    return float(np.trapezoid(y, x) / (hi - lo)) if hi > lo else float(np.interp(lo, lam, vals))


@lru_cache(maxsize=None)
def _basis(wl_key: tuple[float, ...]) -> np.ndarray:
    wl = np.asarray(wl_key)
    t = _table()
    step = np.gradient(wl) if wl.size > 1 else np.array([10.0])
    out = np.empty((len(BASIS_ORDER), wl.size))
    for j, c in enumerate(wl):
        lo = max(c - step[j] / 2, PBRT_RANGE_NM[0])
        hi = min(c + step[j] / 2, PBRT_RANGE_NM[1])
        for i in range(len(BASIS_ORDER)):
            out[i, j] = _segment_average(t[:, 0], t[:, i + 1], lo, hi)
    return out


def illuminant_basis_pbrt(wavelengths: np.ndarray = WAVELENGTHS_31) -> np.ndarray:
    """The 7 illuminant basis spectra ``(7, B)`` (order :data:`BASIS_ORDER`) at the bands."""
    return _basis(tuple(np.asarray(wavelengths, dtype=np.float64).tolist()))


def smits_coefficients_pbrt(rgb: np.ndarray) -> np.ndarray:
    """Smits' weights ``(..., 7)`` of white, cyan, magenta, yellow, red, green, blue."""
    rgb = np.asarray(rgb, dtype=np.float64)
    r, g, b = rgb[..., 0], rgb[..., 1], rgb[..., 2]
    c = np.zeros(rgb.shape[:-1] + (7,))
    r_min = (r <= g) & (r <= b)
    g_min = ~r_min & (g <= r) & (g <= b)
    b_min = ~r_min & ~g_min
    # r minimal: white r; then cyan up to min(g, b), blue or green for the rest
    m = r_min & (g <= b)
    c[m, 0], c[m, 1], c[m, 6] = r[m], g[m] - r[m], b[m] - g[m]
    m = r_min & (g > b)
    c[m, 0], c[m, 1], c[m, 5] = r[m], b[m] - r[m], g[m] - b[m]
    # g minimal: magenta, then blue or red
    m = g_min & (r <= b)
    c[m, 0], c[m, 2], c[m, 6] = g[m], r[m] - g[m], b[m] - r[m]
    m = g_min & (r > b)
    c[m, 0], c[m, 2], c[m, 4] = g[m], b[m] - g[m], r[m] - b[m]
    # b minimal: yellow, then green or red
    m = b_min & (r <= g)
    c[m, 0], c[m, 3], c[m, 5] = b[m], r[m] - b[m], g[m] - r[m]
    m = b_min & (r > g)
    c[m, 0], c[m, 3], c[m, 4] = b[m], g[m] - b[m], r[m] - g[m]
    return c


def RGB_to_spectra_Smits1999_PBRT(rgb: np.ndarray, wavelengths: np.ndarray = WAVELENGTHS_31
                                  ) -> np.ndarray:
    """Illuminant spectra ``(..., B)`` float32 of linear RGB ``(..., 3)``, as pbrt-v3."""
    spec = smits_coefficients_pbrt(rgb) @ illuminant_basis_pbrt(wavelengths)
    return np.clip(spec * PBRT_ILLUMINANT_SCALE, 0.0, None).astype(np.float32)


class SmitsPBRT:
    """SSR-model wrapper (``name``, ``wavelengths``, ``__call__``) for :mod:`mehs.render.maps`."""

    name = "smits-pbrt"
    wavelengths = WAVELENGTHS_31

    def __call__(self, rgb: np.ndarray) -> np.ndarray:
        return RGB_to_spectra_Smits1999_PBRT(rgb, self.wavelengths)
