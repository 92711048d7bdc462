"""The reference's DN/ms per column and band, its uncertainty, and whether it fills the view.

Split from :mod:`mehs.calibration.calibrate`. Two regions (design.md §3.5):

- the white-reference line (one averaged line per exposure): :func:`white_dn_per_ms`;
- scan lines of the fused capture (a sphere or panel filling the view):
  :func:`frame_dn_per_ms`.

A per-column flat field is only as good as the reference's coverage of the slit: a
sphere port or panel narrower than the view leaves columns with stray light or
nothing, whose responsivity would come out ×50–×1000 too small and their radiance as
much too large. :func:`check_columns_filled` and the line check of
:func:`frame_dn_per_ms` refuse that by name (:data:`FILL_FRACTION`). Non-uniformity of
the reference itself across the slit cannot be told from vignetting and goes into the
flat field; it is reported as the column profile's range, not corrected.
"""

from __future__ import annotations

import re
from typing import Any

import numpy as np

from mehs.errors import InputError

#: a column (line) of the reference with less than this fraction of the brightest columns'
#: (lines') signal is not filled by the reference. Optics fall-off at a slit's ends is
#: 10–50 % (a flat field must keep it); stray light beside a sphere's port a few per cent.
#: Columns in a port edge's penumbra above this are not told from vignetting.
FILL_FRACTION = 0.25
#: columns needed for the white line's noise estimate from column-to-column differences
MIN_NOISE_COLUMNS = 8


def _runs(idx: np.ndarray) -> list[tuple[int, int]]:
    """Contiguous runs ``[(first, last), ...]`` of ascending integer indices."""
    if idx.size == 0:
        return []
    cut = np.flatnonzero(np.diff(idx) != 1)
    starts = np.concatenate(([idx[0]], idx[cut + 1]))
    ends = np.concatenate((idx[cut], [idx[-1]]))
    return [(int(a), int(b)) for a, b in zip(starts, ends)]


def _fmt_runs(runs: list[tuple[int, int]]) -> str:
    return ", ".join(f"{a}" if a == b else f"{a}-{b}" for a, b in runs)


def _longest(runs: list[tuple[int, int]]) -> tuple[int, int]:
    return max(runs, key=lambda r: r[1] - r[0])


def parse_columns(columns: Any, samples: int, source: Any = None) -> tuple[int, int] | None:
    """``"A-B"`` (0-based, inclusive) → ``(A, B)``; None stays None."""
    if columns is None:
        return None
    m = re.fullmatch(r"\s*(\d+)\s*-\s*(\d+)\s*", str(columns))
    if m is None:
        raise InputError(f"columns must be 'A-B' (0-based, inclusive), got {columns!r}")
    a, b = int(m.group(1)), int(m.group(2))
    if not (0 <= a <= b < samples):
        raise InputError(f"columns {a}-{b} outside the capture's 0-{samples - 1}", source)
    return a, b


#: the level a column (line) is compared with: the brightest columns' (90th percentile), not
#: the median's, which a reference filling less than half the slit would make one of the unlit
FILL_PERCENTILE = 90.0


def column_profile(dn: np.ndarray) -> np.ndarray:
    """float64 ``(samples,)``: each column's signal over the brightest columns'
    (:data:`FILL_PERCENTILE`), median over bands."""
    with np.errstate(invalid="ignore", divide="ignore"):
        q = dn / np.percentile(dn, FILL_PERCENTILE, axis=0, keepdims=True)
    return np.nanmedian(np.where(np.isfinite(q), q, np.nan), axis=1)


def check_columns_filled(dn: np.ndarray, source: Any = None) -> np.ndarray:
    """Refuse a reference that leaves columns of ``dn`` ``(samples, bands)`` unlit.

    Returns the column profile (:func:`column_profile`).
    """
    prof = column_profile(dn)
    dim = ~(prof >= FILL_FRACTION)
    if dim.any() and prof.size > 1:
        lit = _runs(np.flatnonzero(~dim))
        a, b = _longest(lit) if lit else (0, prof.size - 1)
        worst = float(np.nanmin(prof))
        raise InputError(
            f"the reference fills columns {_fmt_runs(lit) or 'none'} only: columns "
            f"{_fmt_runs(_runs(np.flatnonzero(dim)))} get less than {FILL_FRACTION:.0%} of the "
            f"brightest columns' signal (down to {worst:.1%}: outside the sphere's port or the "
            "panel?); a flat field there would make their radiance up to "
            f"×{1 / max(worst, 1e-6):.3g} too large. Make the reference fill the slit, or "
            f"calibrate with --no-flat-field --columns {a}-{b} (one responsivity per band "
            "from the filled columns, applied to every column)", source)
    return prof


def reduce_columns(dn: np.ndarray, rel: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """One responsivity per band: the mean over columns, and its uncertainty *as applied to a column*.

    The mean's statistical error is combined with the columns' spread about it (the flat
    field left out: vignetting, PRNU), less the part of that spread the per-column noise
    explains. Returns ``(dn (1, bands), rel (1, bands), spread (bands,))``.
    """
    ns = dn.shape[0]
    m = dn.mean(axis=0)
    sem2 = np.mean(rel ** 2, axis=0) / ns
    if ns > 1:
        spread2 = np.maximum(np.var(dn / m[None], axis=0, ddof=1) - np.mean(rel ** 2, axis=0), 0.0)
    else:
        spread2 = np.zeros_like(m)
    return m[None], np.sqrt(sem2 + spread2)[None], np.sqrt(spread2)


def column_noise(dn: np.ndarray) -> np.ndarray:
    """float64 ``(bands,)``: relative noise of one column's ``dn`` ``(samples, bands)``.

    From the second difference across columns (it cancels a flat field's linear trend;
    var = 6σ² for independent noise), a robust (MAD) scale, smoothed over ±3 bands. A
    pixel-to-pixel responsivity pattern (PRNU) counts as noise here: an upper bound then.
    """
    d2 = dn[:-2] - 2 * dn[1:-1] + dn[2:]
    sig = 1.4826 * np.median(np.abs(d2), axis=0) / np.sqrt(6.0)
    rel = sig / np.abs(np.median(dn, axis=0))
    if rel.size >= 7:
        from scipy.ndimage import median_filter

        rel = median_filter(rel, size=7, mode="nearest")
    return rel


def white_dn_per_ms(bracket, response, saturation: np.ndarray,
                    bands: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(samples, bands) DN/ms of the white-reference line and its relative uncertainty.

    ``bands``: the indices to be calibrated (only they must have a usable exposure).
    The longest usable exposure is taken. Its uncertainty is measured across columns
    (:func:`column_noise`): one averaged line per exposure has no spread of its own, and
    the spread of two or three exposures' estimates scattered 0.4–4.5× about the truth
    (simulated captures with 6 noise seeds).
    """
    from mehs.synthesis.fuse import _dark_mode, _lineariser

    if any(w is None for w in bracket.white):
        raise InputError("the capture has no white reference line in every exposure; use "
                         "--region frame (a reference filling the view)", bracket.source)
    L = 1 << bracket.bit_depth
    lin = _lineariser(response, _dark_mode(response), bracket.bit_depth,
                      [d is not None for d in bracket.darks])
    est, use = [], []
    for j, (w, d, t) in enumerate(zip(bracket.white, bracket.darks, bracket.times_ms)):
        w = np.asarray(w, dtype=np.float64)
        dk = np.zeros_like(w) if d is None else np.asarray(d, dtype=np.float64)
        y = np.asarray(lin(w, dk, j), dtype=np.float64)
        est.append(y / t)
        # enough signal to matter, far enough from saturation for the mean of lines
        use.append((w < np.minimum(saturation, 0.98 * (L - 1))[None, :]) & ((w - dk) > 50))
    est, use = np.stack(est)[..., bands], np.stack(use)[..., bands]
    if not use.any(axis=0).all():
        s, b = np.argwhere(~use.any(axis=0))[0]
        raise InputError(f"the white reference is saturated or too dark in every exposure at "
                         f"column {s}, {bracket.wavelengths[bands[b]]:.2f} nm", bracket.source)
    last = (use.shape[0] - 1) - np.argmax(use[::-1], axis=0)
    best = np.take_along_axis(est, last[None], axis=0)[0]
    if best.shape[0] >= MIN_NOISE_COLUMNS:
        return best, np.broadcast_to(column_noise(best), best.shape).copy()
    # too few columns to measure the noise across them: the exposures' spread
    n = use.sum(axis=0)
    with np.errstate(invalid="ignore", divide="ignore"):
        mean = np.where(use, est, 0).sum(0) / np.maximum(n, 1)
        var = np.where(use, (est - mean) ** 2, 0).sum(0) / np.maximum(n - 1, 1)
        rel = np.sqrt(var / np.maximum(n, 1)) / np.abs(best)
    fill = np.median(rel[n >= 2]) if np.any(n >= 2) else 0.01
    return best, np.where(n >= 2, rel, fill)


def region_rows(region: Any, bracket) -> np.ndarray | None:
    """Scan lines of ``region`` (``"frame"``, ``"lines:A-B"``), or None for ``"white"``.

    Checked before any work: a misspelt region (``"Frame"``, ``"whites"``) once
    failed with an IndexError deep in the calibration, and any ``"<word>:A-B"``
    (``"frame:0-9"``) was silently taken for ``"lines:A-B"``.
    """
    nl = bracket.shape[0]
    if region == "white":
        return None
    if region == "frame":
        return np.arange(nl)
    m = re.fullmatch(r"lines:\s*(\d+)\s*-\s*(\d+)\s*", region) if isinstance(region, str) else None
    if m is None:
        raise InputError(f"region must be 'white', 'frame' or 'lines:A-B' (0-based, inclusive), "
                         f"got {region!r}")
    a, b = int(m.group(1)), int(m.group(2))
    if not (0 <= a <= b < nl):
        raise InputError(f"region lines {a}-{b} outside the capture's 0-{nl - 1}", bracket.source)
    return np.arange(a, b + 1)


def frame_dn_per_ms(bracket, response, rows: np.ndarray, saturation,
                    bands: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """DN/ms ``(samples, len(bands))`` of the scan lines ``rows`` of the fused frame.

    The mean over lines, its standard error as the uncertainty. Lines with less than
    :data:`FILL_FRACTION` of the brightest lines' signal (the reference left the view) are
    refused by name, with the ``lines:A-B`` region that avoids them.
    """
    from mehs.synthesis.fuse import fuse_bracket

    res = fuse_bracket(bracket, response=response, ghosts="off", saturation=saturation,
                       check_response=False)
    x = np.asarray(res.radiance.data, dtype=np.float64)[rows][..., bands]
    ok = (res.mask[rows] == 0)[..., None] & np.isfinite(x) & (x > 0)
    if rows.size > 1:
        with np.errstate(invalid="ignore", divide="ignore"):
            q = np.where(ok, x, np.nan) / np.nanpercentile(np.where(ok, x, np.nan),
                                                            FILL_PERCENTILE, axis=0, keepdims=True)
            prof = np.nanmedian(q.reshape(rows.size, -1), axis=1)
        # a line with no usable pixel at all (saturated) is left to the check below
        dim = prof < FILL_FRACTION
        if dim.any():
            lit = _runs(rows[~dim])
            a, b = _longest(lit) if lit else (int(rows[0]), int(rows[-1]))
            raise InputError(f"the reference fills lines {_fmt_runs(lit) or 'none'} only: lines "
                             f"{_fmt_runs(_runs(rows[dim]))} get less than {FILL_FRACTION:.0%} "
                             "of the brightest lines' signal (the reference left the view?); "
                             f"give --region lines:{a}-{b}", bracket.source)
    n = ok.sum(axis=0)
    if np.any(n < 1):
        s, b = np.argwhere(n < 1)[0]
        raise InputError(f"no usable reference line at column {s}, "
                         f"{bracket.wavelengths[bands[b]]:.2f} nm (saturated in every exposure?)",
                         bracket.source)
    mean = np.where(ok, x, 0).sum(0) / n
    var = np.where(ok, (x - mean) ** 2, 0).sum(0) / np.maximum(n - 1, 1)
    rel = np.sqrt(var / n) / mean
    return mean, rel
