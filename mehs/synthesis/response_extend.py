"""The levels a bracket ties together, and the response curve above them.

Debevec–Malik recovery learns ``g`` at a level only from pixels seen there *and* in
another exposure (an unsaturated, weighted pair): a pixel with one usable exposure adds no
equation, its ``E`` being free. Above the highest paired level the curve is the prior's:
the log-domain smoothness ``Σ g''²`` continues ``g`` as a straight line in ``z`` — an
exponential ``f = exp g`` — and a merge reads any sample there through it. A bracket whose
longest exposure sees only a dark part of the scene while the shortest sees a bright
window at levels its neighbour saturates leaves most of the range unpaired: on the
simulator's ``window`` scene (gamma-0.8 sensor, 2 exposures 0.5/2 ms) the pairs reach level
470 of 4095, the window is read at 1540–4013, and the straight continuation put it 17×
too bright relative to the chart (curve 20× off the truth at the top), while the
self-check, which merges and compares only well-exposed pixels, passed it.

Above the covered levels the curve is continued as a *power law* (``g`` straight in
``ln z``) with the slope ``d g / d ln z`` of the covered top octave: exact for a linear
sensor (``g = ln z``) and for a gamma sensor on raw levels (``f ∝ z^{1/γ}``, the black level
being added before the response), and the shape the rounds' prior already takes between
tied levels. It remains an assumption — an S-curve's knee above the data is not seen — so
:mod:`mehs.synthesis.response_check` also reports how much of the bracket is read there
(:func:`read_beyond_coverage`) and calls such a curve undetermined.
"""

from __future__ import annotations

import numpy as np

#: The power law is fitted over ``[hi / COVERED_SPAN, hi]``: the covered top octave (its
#: slope in ``ln z`` is what a power law continues; a longer span mixes in the bend the
#: black level puts near the dark level).
COVERED_SPAN = 2.0
#: A sample read above ``EXTRAPOLATION_MARGIN × hi`` (the highest paired level) counts as
#: read through the extrapolated curve (:func:`read_beyond_coverage`); just above ``hi`` the
#: continuation is as good as the curve at ``hi``.
EXTRAPOLATION_MARGIN = 1.25


def covered_top(Z: np.ndarray, level_w: np.ndarray, *, per_channel: bool = False
                ) -> np.ndarray | int:
    """The highest level tied to another exposure by some sample.

    ``Z`` int ``(N, P[, C])`` sampled levels (``L − 1`` saturated), ``level_w`` ``(L,)`` the
    level weighting (0 at the clipped ends). A sample counts where it has weight and its
    pixel (in that channel) has another weighted exposure. Returns an int (all channels
    pooled), or with ``per_channel`` int64 ``(C,)``; 0 where nothing is paired.
    """
    Z = np.asarray(Z)
    if Z.ndim == 2:
        Z = Z[:, :, None]
    ok = level_w[Z] > 0
    paired = ok & (ok.sum(axis=1, keepdims=True) >= 2)
    top = np.where(paired, Z, 0).max(axis=(0, 1))            # (C,)
    return top.astype(np.int64) if per_channel else int(top.max())


def extend_power_law(g: np.ndarray, hi: np.ndarray | int, gauge: int | None = None) -> np.ndarray:
    """``g`` (C, L) (or (L,)) continued above ``hi`` (per row) as ``g(hi) + s·ln(z/hi)``,
    ``s`` the secant slope of ``g`` against ``ln z`` over ``[hi/COVERED_SPAN, hi]``.

    Rows whose ``hi`` leaves no such octave (``hi < 4``), whose slope is not positive, or
    whose ``hi`` leaves only the clipped end level ``L − 1`` above it (a saturated sample's
    mark, never read as a value) are returned unchanged: there the solve is Debevec and
    Malik's own (their ``gsolve``, to 1e-7). ``gauge``: a level whose value
    is kept (the curve is shifted by one constant after the continuation), e.g.
    ``Z_mid`` for the gauge ``g(Z_mid) = ln Z_mid``; None leaves the covered part as it is.
    Returns float64 of ``g``'s shape.
    """
    g = np.array(g, dtype=np.float64, copy=True)
    one = g.ndim == 1
    G = g[None] if one else g
    L = G.shape[1]
    his = np.broadcast_to(np.asarray(hi, dtype=np.int64), (G.shape[0],))
    lev = np.arange(L, dtype=np.float64)
    for c, h in enumerate(his):
        h = int(h)
        lo = int(np.floor(h / COVERED_SPAN))
        if h < 4 or h >= L - 2 or lo < 1:
            continue
        s = (G[c, h] - G[c, lo]) / np.log(h / lo)
        if not (np.isfinite(s) and s > 0):
            continue
        before = G[c, gauge] if gauge is not None else None
        G[c, h + 1:] = G[c, h] + s * np.log(lev[h + 1:] / h)
        if gauge is not None:
            G[c] += before - G[c, gauge]
    return G[0] if one else G


def read_beyond_coverage(raw: list[np.ndarray], darks: list, saturation: np.ndarray,
                         hi: int) -> dict:
    """How much of a bracket a curve covering levels up to ``hi`` reads by extrapolation.

    ``raw``: the exposures' raw levels, each ``(lines, samples, bands)`` (a subset of lines
    will do); ``darks``: each exposure's raw dark ``(samples, bands)`` or None;
    ``saturation`` ``(bands,)``. A (pixel, band) is read beyond the coverage when one of its
    unsaturated samples lies above ``EXTRAPOLATION_MARGIN·hi`` — the merge weighs the
    highest unsaturated sample most, so such a value dominates its estimate. Returns
    ``read_beyond_coverage`` (fraction of the pixel-bands with an unsaturated sample),
    ``read_beyond_pixels`` (fraction of pixels with such a band), ``covered_top_level``
    (``hi``) and ``read_max_level`` (the highest unsaturated level read).
    """
    sat = np.asarray(saturation, dtype=np.float64)
    lim = EXTRAPOLATION_MARGIN * hi
    beyond = None
    usable = None
    top = 0.0
    for j, x in enumerate(raw):
        x = np.asarray(x)
        ok = x < sat
        if darks[j] is not None:
            ok &= x > np.asarray(darks[j])[None]
        b = ok & (x > lim)
        beyond = b if beyond is None else beyond | b
        usable = ok if usable is None else usable | ok
        if ok.any():
            top = max(top, float(x[ok].max()))
    n = int(usable.sum())
    return {"read_beyond_coverage": float(beyond.sum() / n) if n else 0.0,
            "read_beyond_pixels": float(beyond.any(axis=-1).mean()),
            "covered_top_level": int(hi), "read_max_level": top}
