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
response undetermined       ``response_uncertainty`` (median, relative;   > 0.02
                            :mod:`mehs.synthesis.response_check`)
uncalibrated                ``radiometric_unit`` is DN/ms                 allowed
==========================  ============================================  =========

Figures that are unknown (``None``, e.g. ghosts for ``--from-hs`` cubes) are
not judged. Failed scenes stay in the manifest with their reasons; only
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

    def __post_init__(self):
        for name in ("max_ghost_fraction", "max_saturated_fraction", "max_invalid_fraction"):
            v = getattr(self, name)
            if not (v is not None and 0 <= v <= 1):  # NaN fails too
                raise InputError(f"{name} must be a fraction between 0 and 1, got {v}")
        v = self.min_dynamic_range_stops
        if v is not None and not (math.isfinite(v) and v >= 0):
            raise InputError(f"min_dynamic_range_stops must be >= 0 stops, got {v}")
        v = self.max_response_uncertainty
        if v is not None and not (math.isfinite(v) and v >= 0):
            raise InputError(f"max_response_uncertainty must be >= 0, got {v}")
        if int(self.min_exposures) < 1:
            raise InputError(f"min_exposures must be at least 1, got {self.min_exposures}")

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

    def over(key: str, limit: float, text: str) -> None:
        v = q.get(key)
        if v is not None and v > limit:
            reasons.append(f"{text} {v:.4g} > {limit:g}")

    n = q.get("n_exposures")
    if n is not None and n < rules.min_exposures:
        reasons.append(f"only {n} complete exposure(s) < {rules.min_exposures}")
    over("ghost_fraction", rules.max_ghost_fraction, "ghost fraction")
    over("saturated_fraction", rules.max_saturated_fraction, "saturated-in-all fraction")
    over("invalid_fraction", rules.max_invalid_fraction, "invalid fraction")
    dr = q.get("dynamic_range_stops")
    if dr is not None and dr < rules.min_dynamic_range_stops:
        reasons.append(f"dynamic range {dr:.3g} stops < {rules.min_dynamic_range_stops:g}")
    ru = q.get("response_uncertainty")
    if q.get("response_undetermined") and (ru is None or rules.max_response_uncertainty is None):
        reasons.append("response curve undetermined by the bracket (capture a response ladder "
                       "and build with --response)")
    elif ru is not None and rules.max_response_uncertainty is not None:
        over("response_uncertainty", rules.max_response_uncertainty,
             "response curve undetermined: uncertainty (use a ladder curve, --response)")
    unit = q.get("radiometric_unit")
    if rules.require_calibration and unit is not None and unit.startswith("DN"):
        reasons.append(f"not radiometrically calibrated ({unit})")
    return ("fail" if reasons else "pass"), reasons
