"""Is a recovered response curve determined by its bracket? A self-consistency check.

Debevec–Malik recovery ties level ``z`` of one exposure to the level of the same
pixel in the next: with three exposures ×30–×150 apart these ties jump across
most of the range, and the shape *between* the tied levels is set by the
smoothness prior, not by the data. The error is then systematic — a curve
recovered from the even pixels agrees with one from the odd pixels — and
silent. Two comparisons expose it:

- **split half** (noise): curves from two disjoint pixel sets (a checkerboard)
  with the same prior; they differ by the sampling noise of the solve;
- **prior sensitivity** (identifiability): the curve with the smoothness λ and
  with ``10·λ``; where the data pin the curve both agree, where the prior fills
  the gaps between tied levels they do not.

Both are measured where they matter, on the merged radiance: the bracket
(a subset of lines) is merged with each curve and the relative uncertainty of a
merged sample is the root sum of squares of half the split-half difference
and the prior difference (one global scale removed: the gauge is free). Its
median and 95th percentile over the usable samples are the figures of merit
(comparing the curves level by level instead weighs the levels near black,
where any curve's relative error is large, and separates badly): a median above
:data:`UNDETERMINED_MEDIAN` means the bracket cannot determine the curve, and
the radiance made with it should not be trusted. The remedy is a *response
ladder* captured once (``mehs capture --ladder``: ≥ 5 exposures ×2–×4 of a
static target), whose curve is saved and reused (``--response curve.json``).

Measured on the simulator's gamma-0.8 lamp bracket (3 exposures ×140, true
median radiance error 36 %): the split halves agree to 0.05 % while λ vs 10λ
give radiance 30 % apart (median) — flagged. A ×4 ladder of 7 exposures of the
same scene (true error 2 %): 0.5 % — determined.

References
----------
- Debevec, P. E. and Malik, J. (1997). Recovering high dynamic range radiance
  maps from photographs. SIGGRAPH 97.
- Grossberg, M. D. and Nayar, S. K. (2003). Determining the camera response
  from images: what is knowable? IEEE TPAMI 25(11), 1455–1467 (the ambiguities
  left by exposure pairs).
"""

from __future__ import annotations

from typing import Any, Callable

import numpy as np

from mehs.synthesis.response import ResponseCurve

#: median relative uncertainty of the linearised signal above which the curve is "undetermined"
UNDETERMINED_MEDIAN = 0.02

#: Largest fraction of a bracket's usable (pixel, band) samples that may be read above the
#: levels its pairs of exposures tie (by :data:`~mehs.synthesis.response_extend.
#: EXTRAPOLATION_MARGIN`), where the curve is extrapolated, before the curve is undetermined
#: (:func:`coverage_verdict`). The simulator's brackets (48², 204 bands; window, lamp and
#: colorchecker scenes; gamma 0.5/0.8; 2, 3, 5 exposures ×4 from 0.05 and 0.5 ms): 0 on
#: every bracket whose pairs reach saturation, 0.9–1.2 % on the window brackets whose
#: shortest exposure alone sees the window (6 % of the pixels).
READ_BEYOND_TOLERANCE = 0.001

ADVICE = ("capture a response ladder once (mehs capture --ladder: >= 5 exposures x2-x4 of a "
          "static target), fuse it with --response debevec, and reuse its response.json "
          "with --response")


def _gauge_free_log_ratio(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``|ln(a/b) − median ln(a/b)|``: one global scale between two radiance maps is free."""
    d = np.log(a) - np.log(b)
    return np.abs(d - np.median(d))


def response_uncertainty(recover: Callable[..., ResponseCurve],
                         merge: Callable[[ResponseCurve], tuple[np.ndarray, np.ndarray]],
                         curve: ResponseCurve, *, shape: tuple[int, int], smoothness: float,
                         factor: float = 10.0) -> dict[str, Any]:
    """The self-consistency check of a recovered curve (module docstring).

    Parameters
    ----------
    recover
        ``recover(smoothness=λ, pool=flat_pixel_indices_or_None) -> ResponseCurve``:
        the same recovery that produced ``curve``, on a pixel subset or with another λ.
    merge
        ``merge(curve) -> (radiance (n, bands) float, usable (n, bands) bool)``: the
        bracket's merge (of a fixed subset of pixels) with a given curve.
    curve
        The curve being checked (all pixels, ``smoothness``).
    shape
        ``(lines, samples)`` of the bracket (for the checkerboard split).
    factor
        The second prior's λ multiplier.

    Returns
    -------
    dict
        ``median`` and ``p95`` of the relative radiance uncertainty over the usable
        merged samples, ``split_half_median``, ``prior_median``, ``determined``
        (``median ≤ threshold``), ``threshold``, ``advice`` when undetermined.
    """
    nl, ns = shape
    idx = np.arange(nl * ns)
    r, c = np.divmod(idx, ns)
    a = recover(smoothness=smoothness, pool=idx[(r + c) % 2 == 0])
    b = recover(smoothness=smoothness, pool=idx[(r + c) % 2 == 1])
    stiff = recover(smoothness=smoothness * factor, pool=None)
    r0, ok = merge(curve)
    maps = [merge(x)[0] for x in (a, b, stiff)]
    ok = ok & (r0 > 0) & np.all([m > 0 for m in maps], axis=0)
    if not ok.any():
        return {"determined": False, "median": None, "p95": None,
                "reason": "no usable merged samples to compare"}
    d_split = _gauge_free_log_ratio(maps[0][ok], maps[1][ok]) / 2.0
    d_prior = _gauge_free_log_ratio(maps[2][ok], r0[ok])
    u = np.expm1(np.sqrt(d_split ** 2 + d_prior ** 2))
    med = float(np.median(u))
    out = {
        "method": "split-half + prior sensitivity (lambda x%g), merged radiance" % factor,
        "median": med, "p95": float(np.percentile(u, 95)),
        "split_half_median": float(np.median(np.expm1(d_split))),
        "prior_median": float(np.median(np.expm1(d_prior))),
        "threshold": UNDETERMINED_MEDIAN,
        "determined": bool(med <= UNDETERMINED_MEDIAN),
        "samples_compared": int(ok.sum()),
    }
    if not out["determined"]:
        out["advice"] = ADVICE
    return out


def coverage_verdict(out: dict, raw: list, darks: list, saturation: np.ndarray,
                     covered_top_level: int | None) -> dict:
    """Add to a check's result ``out`` how much of the bracket is read above the levels its
    pairs tie (:func:`mehs.synthesis.response_extend.read_beyond_coverage` on ``raw``, the
    exposures' raw levels (lines, samples, bands), with their ``darks``) and, above
    :data:`READ_BEYOND_TOLERANCE`, call the curve undetermined with a reason and advice.

    The split halves and λ vs 10·λ cannot see this: they compare merges of well-exposed
    pixels, and every curve they recover continues above the pairs the same way. On the
    simulator's window scene (gamma 0.8, 2 exposures 0.5/2 ms) the window, seen unsaturated
    by the shortest exposure only (levels 1540–4013, pairs up to 470), read 17× too bright
    relative to the chart through the straight continuation, and the check passed it
    (median 0.9 %). ``covered_top_level`` None (a curve from elsewhere): nothing is added.
    Returns ``out``."""
    if covered_top_level is None:
        return out
    from mehs.synthesis.response_extend import EXTRAPOLATION_MARGIN, read_beyond_coverage

    cov = read_beyond_coverage(raw, darks, saturation, int(covered_top_level))
    out.update(cov)
    out["read_beyond_tolerance"] = READ_BEYOND_TOLERANCE
    frac = cov["read_beyond_coverage"]
    if out.get("determined") and frac > READ_BEYOND_TOLERANCE:
        out["determined"] = False
        out["reason"] = (
            f"{frac:.2%} of the usable samples ({cov['read_beyond_pixels']:.1%} of the pixels) "
            f"are read at levels up to {cov['read_max_level']:.0f} that no pair of exposures "
            f"ties (pairs reach level {cov['covered_top_level']}; above "
            f"{EXTRAPOLATION_MARGIN:g}x that the curve is extrapolated, not measured); add "
            "an exposure shorter than the shortest so that the brightest parts are seen "
            "unsaturated by two exposures")
        out["advice"] = ADVICE
    return out


def split_exposure_consistency(bracket, *, fuse_kwargs: dict | None = None) -> dict[str, Any]:
    """Curve + merge from the even and from the odd exposures: do they agree?

    Each half of a bracket (exposures 0, 2, 4, … and 1, 3, 5, …) recovers its own
    response curve and is merged on its own; where both halves have a usable
    estimate, ``|Δ ln E|`` (one global scale removed: each curve has its own
    gauge) measures how well the bracket determines radiance. Needs ≥ 4 exposures.

    Returns
    -------
    dict
        ``median`` and ``p99`` of ``|Δ ln E|``, ``pixels`` compared, and each
        half's exposure times.
    """
    from mehs.synthesis.bracket import Bracket
    from mehs.synthesis.fuse import fuse_bracket

    P = len(bracket.exposures)
    if P < 4:
        from mehs.errors import InputError

        raise InputError(f"the split test needs >= 4 exposures, the bracket has {P}",
                         bracket.source)
    kw = {"response": "debevec", "ghosts": "off", "check_response": False, **(fuse_kwargs or {})}
    maps, masks, times = [], [], []
    for start in (0, 1):
        idx = list(range(start, P, 2))
        half = Bracket([bracket.exposures[i] for i in idx], [bracket.darks[i] for i in idx],
                       [bracket.white[i] for i in idx], bracket.times_ms[idx],
                       bracket.wavelengths, bit_depth=bracket.bit_depth, source=bracket.source)
        res = fuse_bracket(half, **kw)
        maps.append(np.asarray(res.radiance.data, dtype=np.float64))
        masks.append(res.mask == 0)
        times.append(half.times_ms.tolist())
    ok = (masks[0] & masks[1])[..., None] & (maps[0] > 0) & (maps[1] > 0)
    d = _gauge_free_log_ratio(maps[0][ok], maps[1][ok])
    return {"median": float(np.median(d)), "p99": float(np.percentile(d, 99)),
            "pixels": int(ok.sum()), "times_even_ms": times[0], "times_odd_ms": times[1]}
