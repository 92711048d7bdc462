"""Pass/fail rules for dataset scenes (excluded by rule, not by hand).

A scene **fails** when any of these holds (thresholds are :class:`QualityRules`
fields, set from ``mehs build`` options):

==========================  ============================================  =========
rule                        figure                                        default
==========================  ============================================  =========
synthesis failed            reading/fusing raised an error                —
too few exposures           complete exposures in the bracket             < 2
ghosts                      ``ghost_fraction`` (pixels flagged moving)    > 0.01
saturated in every exposure ``saturated_fraction``                        > 0.005
other invalid pixels        ``invalid_fraction`` (mask bit 4)             > 0.05
dynamic range too low       ``dynamic_range_stops``                       < 4.0
unresolved by the noise     ``noise_floor_fraction`` (mask bit 8, ground  off
                            truth SNR < 10: :mod:`mehs.dataset.noisefloor`)
response undetermined       ``response_uncertainty`` (median, relative;   > 0.02
                            :mod:`mehs.synthesis.response_check`)
uncalibrated                ``radiometric_unit`` is DN/ms                 allowed
==========================  ============================================  =========

Unresolved pixels are deep shadows, what an HDR scene is for: they are not scored
(every metric skips mask bit 8), so the rule is off unless ``max_noise_floor_fraction``
sets it (a scene too dim to teach anything).

Figures that are unknown (``None``, e.g. ghosts for ``--from-hs`` cubes) are
not judged; a NaN/Inf figure fails the scene (a broken figure is no pass).
``min_dynamic_range_stops=None`` turns the dynamic-range rule off. A failing
value is reported with the digits needed to tell it from the threshold.
Failed scenes stay in the manifest with their reasons; only
passing scenes enter the splits.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from typing import Any

from mehs.errors import InputError


@dataclass(frozen=True)
class QualityRules:
    """Thresholds of the pass/fail rules (fractions are of all pixels)."""

    max_ghost_fraction: float = 0.01
    max_saturated_fraction: float = 0.005
    max_invalid_fraction: float = 0.05
    min_dynamic_range_stops: float = 4.0
    min_exposures: int = 2
    max_response_uncertainty: float = 0.02
    require_calibration: bool = False
    max_noise_floor_fraction: float | None = None

    def __post_init__(self):
        for name in ("max_ghost_fraction", "max_saturated_fraction", "max_invalid_fraction",
                     "max_noise_floor_fraction"):
            v = getattr(self, name)
            if v is None and name == "max_noise_floor_fraction":   # the rule is off
                continue
            if not (v is not None and 0 <= v <= 1):  # NaN fails too
                raise InputError(f"{name} must be a fraction between 0 and 1, got {v}")
        v = self.min_dynamic_range_stops
        if v is not None and not (math.isfinite(v) and v >= 0):
            raise InputError(f"min_dynamic_range_stops must be >= 0 stops, got {v}")
        v = self.max_response_uncertainty
        if v is not None and not (math.isfinite(v) and v >= 0):
            raise InputError(f"max_response_uncertainty must be >= 0, got {v}")
        n = self.min_exposures
        # a float NaN or a string ("2" from a config file) would crash or mis-compare in judge
        if isinstance(n, bool) or not isinstance(n, (int, float)) or not (
                math.isfinite(n) and n == int(n) and n >= 1):
            raise InputError(f"min_exposures must be a whole number of at least 1, got {n!r}")
        object.__setattr__(self, "min_exposures", int(n))

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)


def judge(quality: dict[str, Any], rules: QualityRules = QualityRules(),
          error: str | None = None) -> tuple[str, list[str]]:
    """``("pass"|"fail", reasons)`` for a scene's quality figures.

    Parameters
    ----------
    quality
        Keys ``ghost_fraction``, ``saturated_fraction``, ``invalid_fraction``,
        ``dynamic_range_stops``, ``n_exposures`` (any may be missing or None).
    error
        The synthesis error message, if the scene could not be built.
    """
    reasons: list[str] = []
    if error:
        reasons.append(f"synthesis failed: {error}")
    q = quality or {}

    def figure(key: str, text: str) -> float | None:
        """The figure, or None when unknown; a NaN/Inf figure is a failure, not a pass
        (every comparison with NaN is False, so it slipped through every rule)."""
        v = q.get(key)
        if v is None:
            return None
        if not math.isfinite(v):
            reasons.append(f"{text} is not a finite number ({v})")
            return None
        return v

    def over(key: str, limit: float | None, text: str, advice: str = "") -> None:
        v = figure(key, text)
        if v is not None and limit is not None and v > limit:
            reasons.append(f"{text} {_beside(v, limit)} > {limit:g}{advice}")

    n = q.get("n_exposures")
    if n is not None and n < rules.min_exposures:
        reasons.append(f"only {n} complete exposure(s) < {rules.min_exposures}")
    over("ghost_fraction", rules.max_ghost_fraction, "ghost fraction")
    over("saturated_fraction", rules.max_saturated_fraction, "saturated-in-all fraction")
    over("invalid_fraction", rules.max_invalid_fraction, "invalid fraction")
    over("noise_floor_fraction", rules.max_noise_floor_fraction,
         "fraction not resolved above the noise")
    dr = figure("dynamic_range_stops", "dynamic range")
    lim = rules.min_dynamic_range_stops
    if dr is not None and lim is not None and dr < lim:  # None: the rule is off
        reasons.append(f"dynamic range {_beside(dr, lim)} stops < {lim:g}")
    ru = q.get("response_uncertainty")
    # undetermined with a small uncertainty: the check's exposure-consistency test failed
    # (a biased curve, which split halves and λ vs 10λ cannot see)
    if q.get("response_undetermined") and (ru is None or rules.max_response_uncertainty is None
                                           or ru <= rules.max_response_uncertainty):
        reasons.append("response curve undetermined by the bracket (capture a response ladder "
                       "and build with --response)")
    elif ru is not None and rules.max_response_uncertainty is not None:
        over("response_uncertainty", rules.max_response_uncertainty,
             "response curve undetermined: uncertainty",
             " (use a ladder curve, --response)")
    unit = q.get("radiometric_unit")
    if rules.require_calibration and unit is not None and unit.startswith("DN"):
        reasons.append(f"not radiometrically calibrated ({unit})")
    return ("fail" if reasons else "pass"), reasons


def _beside(value: float, limit: float) -> str:
    """``value`` with enough significant digits to differ from ``limit`` when it does
    (4 stops < 4 or 0.01 > 0.01 read as a rule firing on an equal value)."""
    for digits in range(3, 16):
        text = f"{value:.{digits}g}"
        if float(text) != limit or value == limit:
            return text
    return repr(value)
