"""Named lights from colour-science, as functions of wavelength out to the near infrared.

colour-science tabulates most illuminants and light sources to 780 nm (the ISO 7589 set to
690 nm); a Specim IQ band reaches 1004 nm. How a light continues past its table is a physical
choice, made here once for :mod:`mehs.capture.scene` and :mod:`mehs.scenes.library`:

- CIE illuminant A is its defining formula (CIE 015:2018, eq. 4.1) at every wavelength.
- The CIE daylight illuminants D50, D55, D65, D75 are the CIE D series at their nominal CCT
  (the table CIE 015 gives runs to 830 nm; colour-science's copies stop at 780 nm), then the
  mean of their last 20 nm.
- Incandescent (tungsten-filament) lamps continue as Planck's law at the temperature that fits
  their table from 500 nm on, scaled to the mean of their last 20 nm: a filament is close to a
  grey body and keeps rising into the near infrared (a flat continuation from 690 or 780 nm is
  18–24 % low at 1000 nm).
- Every other light (discharge, fluorescent, LED) holds the mean of its last 20 nm, which keeps
  a discharge lamp's continuum, not its last line.

Nothing is extrapolated below the table's first value or to negative values.

References
----------
- CIE 015:2018 Colorimetry, 4th ed. (illuminant A, eq. 4.1; D series, §4.1.2 and Table 6).
- Wyszecki & Stiles (1982), Color Science, 2nd ed., §1.2 (tungsten as a near grey body).
"""

from __future__ import annotations

import re
from typing import Callable

import numpy as np

from mehs.errors import InputError

#: Tabulated lights that are tungsten filaments (continued by Planck's law past their table).
INCANDESCENT = frozenset({
    "Incandescent", "60 A/W (Soft White)", "Neodimium Incandescent",
    "ISO 7589 Studio Tungsten", "ISO 7589 Photoflood",
    "ISO 7589 Sensitometric Studio Tungsten", "ISO 7589 Sensitometric Photoflood"})

_D_NAME = re.compile(r"D(\d\d)")
# the D series' nominal CCTs were set with c₂ = 1.4380e-2 m·K; colour-science's CCT_to_xy_CIE_D
# takes the CCT on today's scale (c₂ = 1.4388e-2), so D65 is 6500·1.4388/1.4380 ≈ 6504 K
_C2_RESCALE = 1.4388 / 1.4380


def planck(wavelengths_nm, kelvin: float) -> np.ndarray:
    """Planck's law at ``kelvin`` K up to a constant (``λ⁻⁵/(exp(c₂/λT) − 1)``, λ in m, c₂ =
    1.4388e-2 m·K as ``colour.sd_blackbody``), shaped like the input."""
    lam = np.asarray(wavelengths_nm, dtype=np.float64) * 1e-9
    return lam ** -5 / np.expm1(1.4388e-2 / (lam * kelvin))


def cie_illuminant_a(wavelengths_nm) -> np.ndarray:
    """CIE illuminant A by its definition (CIE 015:2018 eq. 4.1): 100 at 560 nm.

    ``100 (560/λ)⁵ (exp(1.435e7 / (2848·560)) − 1) / (exp(1.435e7 / (2848 λ)) − 1)``, λ in nm.
    This is Planck's law with c₂ = 1.435e-2 m·K at 2848 K — with today's c₂ (1.4388e-2) that
    is 2855.5 K, not exactly 2856 K (0.07 % apart at 400 nm).
    """
    lam = np.asarray(wavelengths_nm, dtype=np.float64)
    return 100.0 * (560.0 / lam) ** 5 * np.expm1(1.435e7 / (2848.0 * 560.0)) / np.expm1(1.435e7 / (2848.0 * lam))


def _tail(w: np.ndarray, v: np.ndarray, tail_nm: float = 20.0) -> tuple[np.ndarray, np.ndarray]:
    keep = w >= w[-1] - tail_nm
    return w[keep], v[keep]


def _table_fn(w: np.ndarray, v: np.ndarray, beyond: Callable[[np.ndarray], np.ndarray] | None = None):
    """Linear interpolation inside the table; first value below it; ``beyond`` (default: the
    mean of the last 20 nm) above it."""
    hi = float(_tail(w, v)[1].mean())

    def fn(x):
        x = np.asarray(x, dtype=np.float64)
        out = np.interp(x, w, v, left=v[0], right=hi)
        if beyond is not None:
            above = x > w[-1]
            if np.any(above):
                out = np.where(above, beyond(np.where(above, x, w[-1])), out)
        return out
    return fn


def fit_planck_temperature(w: np.ndarray, v: np.ndarray, lo_nm: float = 500.0) -> float:
    """Temperature (K) whose Planck curve best fits the shape of ``v`` (log least squares) from
    ``lo_nm`` to the table's end."""
    from scipy.optimize import minimize_scalar

    k = (w >= lo_nm) & (v > 0)
    if k.sum() < 3:
        raise InputError(f"too few positive values above {lo_nm:g} nm to fit a temperature")
    lv = np.log(v[k])

    def cost(t):
        d = lv - np.log(planck(w[k], t))
        return float(np.var(d))
    return float(minimize_scalar(cost, bounds=(1000.0, 6000.0), method="bounded",
                                 options={"xatol": 0.01}).x)


def light_function(name: str) -> Callable[[np.ndarray], np.ndarray]:
    """``fn(λ nm) → SPD`` (any shape, relative units) of a light named in
    ``colour.SDS_ILLUMINANTS`` or ``colour.SDS_LIGHT_SOURCES``, continued past its table as
    the module notes say."""
    import colour

    if name == "A":
        return cie_illuminant_a
    m = _D_NAME.fullmatch(name)
    if m and name in colour.SDS_ILLUMINANTS:
        xy = colour.temperature.CCT_to_xy_CIE_D(100.0 * int(m.group(1)) * _C2_RESCALE)
        sd = colour.sd_CIE_illuminant_D_series(xy)
        return _table_fn(np.asarray(sd.wavelengths, np.float64), np.asarray(sd.values, np.float64))
    if name in colour.SDS_ILLUMINANTS:
        sd = colour.SDS_ILLUMINANTS[name]
    elif name in colour.SDS_LIGHT_SOURCES:
        sd = colour.SDS_LIGHT_SOURCES[name]
    else:
        raise InputError(f"unknown light {name!r}; use one of colour.SDS_ILLUMINANTS "
                         "(D65, A, HP1, FL2, FL11, LED-B3, …) or colour.SDS_LIGHT_SOURCES")
    w, v = np.asarray(sd.wavelengths, np.float64), np.asarray(sd.values, np.float64)
    if name not in INCANDESCENT:
        return _table_fn(w, v)
    t = fit_planck_temperature(w, v)
    tw, tv = _tail(w, v)
    scale = float(tv.mean() / planck(tw, t).mean())
    return _table_fn(w, v, lambda x: scale * planck(x, t))
