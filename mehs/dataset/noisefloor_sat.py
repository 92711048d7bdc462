"""Which exposures the merge used at a level: the saturation steps of the band noise model.

The merge (:mod:`mehs.synthesis.merge`) pools only an element's *usable* samples: an
exposure saturates above ``X·t_j ≥ ys_j`` (``ys_j`` the linearised saturation level of
exposure ``j`` less its dark) and is dropped a margin below that (``_usable`` in
:mod:`mehs.synthesis._merge_rows`: the shorter exposures' prediction must lie 3σ below
saturation, or the sample's own 3σ when that prediction is the noisier). An element that
saturates the longest exposures is the estimate of the shorter ones alone, noisier than
the all-exposures model by up to ``T/t₀`` in variance (×150 and more for the usual
brackets). Against the simulator (window scene, ×4…×150): ``|hs − truth|/σ`` had std
1.0 where every exposure was usable but 1.9, 3.4, 6.8 and 15 where only 4, 3, 2 or the
shortest one was.

The levels depend on the bracket only (saturation, darks, times, noise), so the fusion
records them (``fusion.json`` ``saturation_linear_dn``, :func:`record_saturation`) and
:func:`usable_limits` turns them into the radiance ``X`` (DN/ms) above which each
exposure is no longer used; the band model then steps at those levels
(:func:`mehs.dataset.noisefloor.band_noise_model`).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from mehs.errors import InputError

#: the key of ``fusion.json`` (and the fusion summary) that holds the levels
SATURATION_KEY = "saturation_linear_dn"


def raw_saturation(summary: dict[str, Any], nb: int) -> np.ndarray | None:
    """float64 ``(nb,)`` raw DN at which the fusion counted a sample saturated, from its
    summary's ``saturation_detected`` record; ``None`` when it has none (a level given by
    the caller is not recorded)."""
    sd = summary.get("saturation_detected")
    if not isinstance(sd, dict):
        return None
    v = sd.get("saturation_dn", sd.get("default_dn"))     # the former only when detected
    if v is None:
        return None
    try:
        return np.broadcast_to(np.asarray(v, dtype=np.float64), (nb,)).copy()
    except ValueError:
        raise InputError(f"the fusion summary's saturation level has {np.size(v)} values, "
                         f"the bracket {nb} bands") from None


def record_saturation(summary: dict[str, Any], bracket, curve) -> None:
    """Add :data:`SATURATION_KEY` to a fusion ``summary`` (in place): float ``(P, bands)``,
    the saturation level of each exposure (ascending times) after the merge's own
    linearisation and dark subtraction, median over columns. Nothing is added when the
    summary does not say the saturation level."""
    from mehs.synthesis.fuse import _lineariser

    nl, ns, nb = bracket.shape
    sat = raw_saturation(summary, nb)
    if sat is None:
        return
    dark_mode = (summary.get("response") or {}).get("dark_mode", "raw")
    has_dark = [d is not None for d in bracket.darks]
    lin = _lineariser(curve, dark_mode, bracket.bit_depth, has_dark)
    raw = np.broadcast_to(sat.astype(np.float32), (ns, nb))
    levels = []
    for j, d in enumerate(bracket.darks):        # a bracket is sorted by time
        d = np.zeros((ns, nb), np.float32) if d is None else np.asarray(d, np.float32)
        if d.ndim == 3:
            d = d.mean(axis=0)
        levels.append(np.median(np.asarray(lin(raw, d, j), np.float64), axis=0))
    summary[SATURATION_KEY] = np.stack(levels).tolist()


def saturation_levels(summary: dict[str, Any], n_exp: int, bands=None) -> np.ndarray | None:
    """float64 ``(P, n)`` of a summary's :data:`SATURATION_KEY` (``bands``: the indices
    kept in the cube, e.g. a calibration's), or ``None`` when it has none."""
    v = summary.get(SATURATION_KEY)
    if v is None:
        return None
    try:
        ys = np.asarray(v, dtype=np.float64)
    except (TypeError, ValueError):
        ys = np.empty(0)
    if ys.ndim != 2 or ys.shape[0] != n_exp or not np.all(np.isfinite(ys)):
        raise InputError(f"fusion.json {SATURATION_KEY!r} must be {n_exp} rows (one per "
                         f"exposure) of finite levels, got shape {ys.shape}")
    if bands is not None:
        bands = np.asarray(bands, dtype=np.int64)
        if bands.size and (bands.max() >= ys.shape[1] or bands.min() < 0):
            raise InputError(f"fusion.json {SATURATION_KEY!r} has {ys.shape[1]} bands, the "
                             f"calibration names band {int(bands.max())}")
        ys = ys[:, bands]
    return ys


def usable_limits(noise: dict[str, Any], times_ms, ys: np.ndarray) -> np.ndarray:
    """float64 ``(P, n)``: the radiance ``X`` (DN/ms) above which the merge no longer uses
    exposure ``j`` of a band, expected (noise-free) value of its choice; non-increasing in
    ``j``.

    ``ys (P, n)``: linearised saturation levels less dark (:func:`record_saturation`).
    Exposure 0 is used below saturation (``X·t₀ < ys₀``); a later one where the shorter
    exposures' prediction lies ``3σ`` below saturation, ``σ²`` the sample's variance plus
    the prediction's — or, where the prediction is over 2× the noisier, the sample's own
    ``3σ`` (the merge's ``_usable``: same constants, same variances, at ``y = X·t``).
    """
    from mehs.dataset.noisefloor import _noise_values
    from mehs.synthesis._merge_rows import PREDICTION_NOISIER2, ROOM_SIGMA2

    t, gain, read, dc, _ = _noise_values(noise, times_ms)
    t = np.sort(t)
    ys = np.maximum(np.asarray(ys, dtype=np.float64), 0.0)
    a = read * read + gain * dc * t
    k2, n2 = float(ROOM_SIGMA2), float(PREDICTION_NOISIER2)
    out = np.empty_like(ys)
    out[0] = ys[0] / t[0]
    for j in range(1, t.size):
        tj, st, sav = t[j], t[:j].sum(), a[:j].sum()
        y = ys[j]

        def vp(x):            # the sample's variance plus its prediction's (DN²)
            return gain * x * tj + a[j] + tj * tj * (gain * x / st + sav / (st * st))

        # the prediction's rule: ys − X·t > 3·sqrt(vp(X)), decreasing in X (bisection)
        lo, hi = np.zeros_like(y), y / tj
        for _ in range(60):
            mid = 0.5 * (lo + hi)
            room = y - mid * tj
            ok = (room > 0) & (room * room > k2 * vp(mid))
            lo, hi = np.where(ok, mid, lo), np.where(ok, hi, mid)
        vown = gain * y + a[j]
        xb = np.maximum(y - np.sqrt(k2 * vown), 0.0) / tj
        own = vp(xb) > n2 * vown            # its own margin decides up to xb
        x = np.where(own & (xb > lo), xb, lo)
        out[j] = np.minimum(x, out[j - 1])
    return out
