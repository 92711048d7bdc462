"""Where the sensor clips, found from the bracket's longest exposure.

The merge counts a raw sample as saturated at ``raw ≥ 0.98·(L − 1)`` unless told
otherwise. A sensor whose pixels clip at their full well (electrons) below the
ADC's largest code, or whose ADC saturates below it (per band or tap), writes
its clipped samples as a plateau at, say, 3600 DN: taken as measurements, they
read bright areas low by as much as the clip is exceeded, silently (the simulator
with a 14 000 e⁻ full well, plateau 3532 DN: samples clipped in the longest exposure
merged 42 % low in the median, up to 86 %).

A clip shows in the longest exposure as a *pile-up* at the top of each band's
raw distribution: many samples within a few DN of the band's maximum (the
plateau, spread only by the noise and column offsets added after the clip),
and few in a window of the same width just below. The top of a smooth
distribution (a bright patch, a glow, an unclipped lamp) is its tail, whose
density falls towards its maximum, and a bright patch's shot noise (tens of DN
near full scale) spreads it far wider than the widest window tried here
(:data:`WINDOWS_DN`, ×L/4096 for deeper ADCs).

Per band (whole lines of the longest exposure, evenly spaced): the smallest
window ``w`` with ``n(max − w … max) ≥`` :data:`MIN_SAMPLES`, at least
:data:`DENSITY_RATIO` times the count in ``max − 2w − 1 … max − w − 1``, and
spread over :data:`MIN_COLUMNS` columns (one hot or stuck column is not a clip)
is the pile-up. The samples of both windows give the clip level (median), the
plateau's upper half its spread ``σ`` (RMS about the median, at least ½ DN: no
unclipped sample lies above a clip), and the saturation threshold is
``min(median − MARGIN_SIGMA·σ, lowest pile-up sample)``: every clipped sample,
in every column, counts as saturated. A threshold at or above the default
(a pile-up at the ADC's largest code) changes nothing, and a band whose samples
reach that code has no clip below it (not searched).

A narrow cluster at the top is not always a clip: a uniform patch in a band
where it is dim (a sodium lamp's core between its lines: 75 DN ± 4) piles up
too. :func:`confirm_clip` tells them apart by the same samples of the next
shorter exposure: a clip lost the shot noise and the scene's variation that the
shorter exposure still shows, so there (dark-subtracted, × the exposure ratio)
they spread more than :data:`SPREAD_RATIO` × ratio times the plateau; an
unclipped cluster spreads at most ratio times more. Samples on the plateau in
the shorter exposure too (clipped in both) confirm it as well.

A full-well clip is one level for the whole sensor: when at least two bands
show one and their levels agree (within :func:`_agreement_dn`), the lowest
threshold also applies to the bands that showed none (too few bright samples in
the lines read: a low-QE band) — unless a band's own maximum lies clearly above
the shared level, evidence that it clips elsewhere.

A threshold that is too low costs only signal-to-noise (the samples above it
come from shorter exposures); one too high biases the radiance. The caller's
``saturation`` always wins.
"""

from __future__ import annotations

import sys
from typing import Any

import numpy as np

#: Pixels read (whole lines, evenly spaced) from the longest exposure: 128 of 512
#: lines of a 512² scan, 13 MB of a 512×512×204 uint16 cube.
PROBE_PIXELS = 65536
#: Top windows tried, DN at 12 bits (scaled by L/4096): a plateau spread up to
#: σ ≈ 10 DN (column offsets and read noise after the clip) fits the widest.
WINDOWS_DN = (2, 4, 8, 16, 32, 64)
#: Samples of a pile-up its level, spread and test are taken from (evenly spaced).
STAT_SAMPLES = 1024
#: Samples a pile-up needs (of the lines read).
MIN_SAMPLES = 16
#: Distinct columns a pile-up needs.
MIN_COLUMNS = 4
#: Density of the top window over the window below it.
DENSITY_RATIO = 5.0
#: Threshold below the plateau's median, in its σ.
MARGIN_SIGMA = 5.0
#: A clip's plateau spreads this many times (× the exposure ratio) less than the
#: same samples of the next shorter exposure, scaled to the longest.
SPREAD_RATIO = 2.0


def _windows(levels: int) -> list[int]:
    s = levels / 4096.0
    return sorted({max(1, int(round(w * s))) for w in WINDOWS_DN})


def _agreement_dn(levels: int) -> float:
    """Plateaus of different bands closer than this are one sensor-wide clip
    (1 % of full scale: per-band black levels differ by a few tens of DN)."""
    return 0.01 * (levels - 1)


def find_pileups(values: np.ndarray, columns: np.ndarray, levels: int,
                 below: float | None = None) -> dict[int, dict[str, Any]]:
    """Per band, the pile-up at the top of ``values`` ``(bands, n)`` raw DN.

    ``columns`` ``(n,)`` is each sample's column. Returns ``{band: {"level_dn",
    "spread_dn", "threshold_dn", "samples", "below", "window_dn", "max_dn"}}`` for the
    bands that have one (see the module notes). A pile-up whose threshold lies below
    ``below`` (None: every one) must also span :data:`MIN_COLUMNS` columns, and has
    ``"columns"``, ``"index"`` and ``"values"`` (at most about 2·:data:`STAT_SAMPLES` of
    its samples, evenly spaced, for :func:`confirm_clip`).
    """
    v = np.asarray(values)
    nb, n = v.shape
    if n == 0:
        return {}
    if not np.issubdtype(v.dtype, np.unsignedinteger):
        # raw DN stored as floats or signed integers: whole codes of the ADC's range
        v = np.clip(np.floor(v), 0, levels - 1).astype(np.uint16 if levels <= 1 << 16 else np.uint32)
    ws = _windows(levels)
    span = 2 * ws[-1] + 1
    m = v.max(axis=1).astype(np.int64)
    found: dict[int, dict[str, Any]] = {}
    for b in range(nb):
        row, mb = v[b], int(m[b])
        if mb >= levels - 1:
            continue          # the ADC's largest code reached: no clip below it in this band
        # counts at max, max − 1, …, max − span: a histogram of the band's codes, no
        # per-sample arrays (a clipped band may have a quarter of its samples there)
        h = np.bincount(row, minlength=mb + 1)[max(0, mb - span):][::-1]
        h = np.pad(h, (0, span + 1 - h.size))
        cum = np.cumsum(h)
        for w in ws:
            n_top, n_below = int(cum[w]), int(cum[2 * w + 1] - cum[w])
            if n_top < MIN_SAMPLES or n_top < DENSITY_RATIO * n_below:
                continue
            # level and spread over the window below too: the smallest window passing
            # may have cut the plateau's lower tail (the continuum there is sparse); the
            # spread from the plateau's upper half, where no unclipped sample lies
            k = np.arange(2 * w + 2)
            hk = h[:2 * w + 2]
            km = int(k[np.searchsorted(np.cumsum(hk), 0.5 * hk.sum())])
            up = hk[:km + 1]
            sd = max(float(np.sqrt(up @ (km - k[:km + 1]) ** 2 / up.sum())), 0.5)
            med = float(mb - km)
            lowest = float(mb - k[:w + 1][h[:w + 1] > 0].max())
            pile = {"level_dn": med, "spread_dn": sd,
                    "threshold_dn": float(np.floor(min(med - MARGIN_SIGMA * sd, lowest))),
                    "samples": n_top, "below": n_below, "window_dn": int(w), "max_dn": float(mb)}
            if pile["threshold_dn"] <= 0:
                break         # a band at the black level (dead, or dark): no clip to find
            if below is None or pile["threshold_dn"] < below:
                sel = np.flatnonzero(row >= mb - w)
                sel = sel[::max(1, sel.size // STAT_SAMPLES)]
                pile["columns"] = int(np.unique(columns[sel]).size)
                if pile["columns"] < MIN_COLUMNS:
                    continue
                pile["index"], pile["values"] = sel, row[sel].astype(np.float64)
            found[b] = pile
            break
    return found


def confirm_clip(pile: dict[str, Any], band: int, short: np.ndarray, columns: np.ndarray,
                 dark_long: np.ndarray | None, dark_short: np.ndarray | None,
                 ratio: float) -> tuple[bool, dict[str, float]]:
    """Whether a pile-up of the longest exposure is a clip, by the same samples in a
    shorter exposure ``short`` (``(bands, n)``; ``ratio`` = t_long / t_short).

    A clipped plateau has lost its shot noise (and the scene's variation), which the
    shorter exposure still carries: its dark-subtracted values, × ``ratio``, spread far
    more than the plateau. An unclipped cluster (a uniform patch: a lamp's core in a
    band it barely emits in) spreads at most ``ratio`` times more there (read noise;
    shot noise √ratio, the scene's own variation 1×). Samples on the plateau in the
    shorter exposure too (clipped in both) are evidence of their own: a scene's cluster
    would sit ``ratio`` times lower.
    """
    i = pile["index"]
    c = columns[i]
    zs = short[band, i].astype(np.float64)
    yl = pile["values"] - (0.0 if dark_long is None else dark_long[c, band])
    ys = ratio * (zs - (0.0 if dark_short is None else dark_short[c, band]))
    sd = max(float(yl.std()), 0.5)
    spread = float(ys.std()) / sd
    both = float(np.mean(zs >= pile["threshold_dn"]))
    # (a dim cluster, ratio times lower in the shorter exposure, may still lie within it)
    apart = float(np.median(yl)) * (1 - 1 / ratio) > 2 * MARGIN_SIGMA * sd
    ok = (apart and both >= 0.5) or spread >= SPREAD_RATIO * ratio
    return ok, {"clipped_in_shorter": round(both, 3), "spread_ratio": round(spread, 2)}


def _read_lines(bracket, j: int, max_pixels: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Evenly spaced whole lines of exposure ``j``, as :func:`mehs.synthesis.noise.probe_bracket`
    reads them: ``(bands, n)`` raw values, their columns ``(n,)`` and the lines read."""
    nl, ns, nb = bracket.shape
    step = max(1, int(np.ceil(nl * ns / max_pixels)))
    lines = np.arange(min(step // 2, nl - 1), nl, step)
    a = np.asarray(bracket.exposures[j].data)
    bil = a.transpose(0, 2, 1)
    # a BIL memmap (Specim's): gather whole lines as stored, one band after another
    block = bil[lines].transpose(1, 0, 2) if bil.flags.c_contiguous else a[lines].transpose(2, 0, 1)
    cols = np.tile(np.arange(ns), lines.size)
    return np.ascontiguousarray(block).reshape(nb, -1), cols, lines


def detect_saturation(bracket, default: float | None = None, *,
                      max_pixels: int = PROBE_PIXELS) -> tuple[np.ndarray, dict[str, Any]]:
    """Per-band saturation thresholds (raw DN, float32 ``(bands,)``) for ``bracket``, and
    what was found (JSON-able: the fusion summary's ``saturation_detected``).

    ``default`` (``0.98·(L − 1)`` if None) is kept for every band with no clip below it.
    """
    L = 1 << int(bracket.bit_depth)
    nb = bracket.shape[2]
    default = 0.98 * (L - 1) if default is None else float(default)
    sat = np.full(nb, default, dtype=np.float64)
    j = len(bracket.exposures) - 1                 # the longest (a bracket is sorted)
    values, cols, lines = _read_lines(bracket, j, max_pixels)
    piles = find_pileups(values, cols, L, below=default)
    below = {b: p for b, p in piles.items() if p["threshold_dn"] < default}
    info: dict[str, Any] = {
        "method": "pile-up at the top of the longest exposure's raw values",
        "exposure_ms": float(bracket.times_ms[j]), "lines_read": int(lines.size),
        "default_dn": default, "detected": False, "shared": False, "bands": [],
    }
    if below:
        short, _, _ = _read_lines(bracket, j - 1, max_pixels)
        ratio = float(bracket.times_ms[j] / bracket.times_ms[j - 1])
        rejected = []
        for b in sorted(below):
            ok, ev = confirm_clip(below[b], b, short, cols, bracket.darks[j],
                                  bracket.darks[j - 1], ratio)
            below[b].update(ev)
            if not ok:
                rejected.append(b)
                del below[b]
                del piles[b]      # a scene's cluster: says nothing about this band's clip
        if rejected:
            info["bands_rejected"] = rejected
    info["detected"] = bool(below)
    if not below:
        return sat.astype(np.float32), info
    bands = sorted(below)
    for b in bands:
        sat[b] = below[b]["threshold_dn"]
    levels = np.array([below[b]["level_dn"] for b in bands])
    shared = len(bands) >= 2 and float(np.ptp(levels)) <= _agreement_dn(L)
    extended: list[int] = []
    if shared:
        # one full well for the whole sensor: bands too dim to show the pile-up in the
        # lines read clip there too — unless their own values rise clearly above it
        thr = float(min(below[b]["threshold_dn"] for b in bands))
        ceiling = float(levels.max()) + _agreement_dn(L)
        bmax = values.max(axis=1).astype(np.float64)
        for b in range(nb):
            if b not in below and b not in piles and bmax[b] <= ceiling and thr < sat[b]:
                sat[b] = thr
                extended.append(b)
    wl = np.asarray(bracket.wavelengths, dtype=np.float64)
    info.update({
        "shared": bool(shared),
        "bands": bands,
        "wavelengths_nm": [round(float(wl[b]), 2) for b in bands],
        "level_dn": [round(below[b]["level_dn"], 2) for b in bands],
        "spread_dn": [round(below[b]["spread_dn"], 2) for b in bands],
        "threshold_dn": [below[b]["threshold_dn"] for b in bands],
        "samples": [below[b]["samples"] for b in bands],
        "samples_below": [below[b]["below"] for b in bands],
        "columns": [below[b]["columns"] for b in bands],
        "spread_ratio": [below[b]["spread_ratio"] for b in bands],
        "clipped_in_shorter": [below[b]["clipped_in_shorter"] for b in bands],
        "bands_extended": extended,
        "saturation_dn": (float(sat[0]) if np.all(sat == sat[0])
                          else [float(s) for s in sat]),
    })
    return sat.astype(np.float32), info


def notice(info: dict[str, Any], source: Any = None) -> str | None:
    """The stderr notice for a detected clip (printed; also returned), or None."""
    if not info.get("detected"):
        return None
    lo, hi = round(min(info["level_dn"])), round(max(info["level_dn"]))
    n_used = len(info["bands"]) + len(info["bands_extended"])
    where = f"{source}: " if source is not None else ""
    msg = (f"mehs: notice: {where}the sensor clips below the ADC's largest code: a pile-up at "
           f"{lo if lo == hi else f'{lo}–{hi}'} DN in {len(info['bands'])} band(s) of the "
           f"{info['exposure_ms']:g} ms exposure; samples from "
           f"{min(info['threshold_dn']):.0f} DN count as saturated in {n_used} band(s) "
           f"(default {info['default_dn']:.0f} DN; --saturation / saturation= overrides)")
    print(msg, file=sys.stderr)
    return msg
