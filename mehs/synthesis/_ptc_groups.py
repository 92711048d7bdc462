"""The per-group photon-transfer statistics of one exposure pair (issue 16).

:mod:`mehs.synthesis.noise` measures the noise model and the linearity of a bracket from
the mean and variance of ``d = y_k − r·y_j`` per signal level; :func:`group_statistics`
computes them for one pair of exposures of the probed samples:

- the groups: quantiles of the instrument (the neighbouring band's ``y_j + y_k``, whose
  noise is independent of the sample's) cut at the edges of cells of its float32 value,
  from an even subset of the samples;
- a robust centre and spread per group (median and MAD of that subset, by one selection:
  no Python loop holding the GIL) and the noise at each sample's own level (the subset's
  photon-transfer line, :func:`_noise_curve`), which set a 5σ clip that holds for a
  group mixing levels (:func:`_group_clip`, :func:`_clip_sigma`);
- the pixels a moving object changed between the two exposures, found by their bands'
  joint departure from those medians, alone and in runs of neighbours
  (:func:`mehs.synthesis._ptc_moving._moving_pixels`) or by a subset sample
  beyond 5σ of its own level, left out whole;
- one pass over every sample (:func:`mehs.synthesis._ptc_kernels.ptc_pass`, stored machine
  code; numpy's :mod:`mehs.synthesis._ptc_numpy` while it compiles): each group's counts
  of all and of saturated samples and the clipped sums.
"""

from __future__ import annotations

import math
from typing import Callable

import numpy as np

# the moving-pixel detector (its own module for length); group_statistics calls it by
# this module's name
from mehs.synthesis._ptc_moving import MOVING_Z, SCORE_BANDS, _moving_pixels  # noqa: F401


def _instrument(y: np.ndarray) -> np.ndarray:
    """The neighbouring band of each band (b ↔ b ^ 1; the last odd one out uses b − 1)."""
    nb = y.shape[-1]
    idx = np.arange(nb) ^ 1
    idx[idx >= nb] = nb - 2 if nb >= 2 else 0
    return idx


#: Bits of the float32 order key that name a cell of :func:`_cell_groups`.
CELL_BITS = 18


def _cell_groups(cells: np.ndarray, groups: int) -> tuple[int, np.ndarray]:
    """``(lo, table)``: table uint16, the group (0 … ``groups − 1``) of each of the run of
    consecutive cells of the instrument's value
    (:func:`mehs.synthesis._ptc_kernels._row_cells`) from ``lo``, the lowest of the good
    samples' ``cells`` (those of the even subset of :func:`group_statistics`;
    non-empty), to the highest.

    Groups are ranges of the instrument holding about equal numbers of good samples,
    bounded at the cell edges nearest to the quantiles ``k/groups``: a sample's group is
    a table lookup of its cell — neither a partition for the quantiles nor a binary
    search per value. Like quantile edges they depend on the instrument only; a cell's
    worth of tied values (one integer level of a dark scene) stays in one group, as
    equal quantiles would leave it (a group may then span no cell).

    From the cells sorted, not counted: the cell holding target rank ``t`` is that of the
    ``⌈t⌉``-th smallest sample, and the samples below and up to it are two binary
    searches. A probe's cells span ~140 k values for ~40 k samples (an instrument that
    crosses zero spans every tiny float magnitude between), so counting them cost
    1–2.5 ms a pair.
    """
    srt = np.sort(cells)
    lo, n = int(srt[0]), srt.size
    target = np.arange(1, groups) * (n / groups)
    at = srt[np.ceil(target).astype(np.int64) - 1]          # the cell of each target rank
    before = np.searchsorted(srt, at, side="left")         # samples in earlier cells
    upto = np.searchsorted(srt, at, side="right")
    last = at.astype(np.int64) - lo
    # the group ends after that cell, or before it when that is nearer the target
    # (non-decreasing: a later target moves the end no earlier)
    last = np.where(target - before < upto - target, last - 1, last)
    bounds = np.concatenate(([0], last + 1, [int(srt[-1]) - lo + 1]))
    return lo, np.repeat(np.arange(groups, dtype=np.uint16), np.diff(bounds))


#: The per-group median and MAD that set the 5σ clip come from about this many samples a
#: group; a group with few samples in that subset uses all of its own. The MAD's error,
#: ~3.6 % of σ at 1024 Gaussian samples, moves the clip by 0.2σ: it then drops < 2e-5 of
#: a Gaussian group's samples instead of < 1e-5, and the variance is summed over all
#: the others. (4096 until issue 16: the medians cost more than the sums they clip.)
CLIP_SAMPLES = 1024


def _stride(n: int, m: int, bands: int) -> int:
    """A step through ``n`` pixel-major samples that keeps about ``m``, coprime with the
    number of bands: the kept samples cover every band and pixel evenly."""
    s = max(1, n // max(m, 1))
    while s > 1 and math.gcd(s, bands) != 1:
        s += 1
    return s


def _order_keys(x: np.ndarray) -> np.ndarray:
    """uint64 keys (below 2**32) of float32-rounded ``x`` that sort like the values: the
    bits of a negative value all flipped, of a positive one the sign bit set — by one
    exclusive or with its sign bit spread (``b >> 31``: all ones or none) on 32-bit
    integers (a ``where`` over 64-bit ones took 3–4× as long, three times a pair)."""
    b = np.ascontiguousarray(x, dtype=np.float32).view(np.int32)
    return (b ^ ((b >> 31) | np.int32(-2 ** 31))).view(np.uint32).astype(np.uint64)


def _group_order(g: np.ndarray, groups: int) -> tuple:
    """What :func:`_group_medians` needs of the groups ``g`` alone — the group half of its
    sort keys (``group << 32``), where each group's middle ranks fall among the sorted
    keys, which groups have samples — shared by its calls over one subset (three a
    pair, each over the same groups)."""
    keys = g.astype(np.uint64)
    keys <<= np.uint64(32)
    count = np.bincount(g, minlength=groups)
    start = np.cumsum(count) - count
    has = count > 0
    return keys, (start + (count - 1) // 2)[has], (start + count // 2)[has], has


def _group_medians(v: np.ndarray, g: np.ndarray, groups: int, order: tuple | None = None
                   ) -> np.ndarray:
    """float64 (groups,) the median of the float32-rounded ``v`` of each group ``g`` (0 for
    an empty group), as ``np.median`` defines it (the mean of the two middle values of
    an even count), from one sort of ``group << 32 | value key``: no Python loop over
    the groups, and the sort releases the GIL, so that the exposure pairs' statistics
    run side by side on threads (a loop of ``np.median`` calls held it for 3–7 ms a
    pair, issue 16). ``order``: :func:`_group_order` of ``g``, when at hand."""
    group_keys, lo, hi, has = _group_order(g, groups) if order is None else order
    keys = group_keys | _order_keys(v)
    # the keys order by group, then value: each group's middle ranks are the same
    # positions of the whole. A whole sort, not a partition at those ranks: numpy's
    # vectorised sort of integer keys took 0.2 ms for a pair's 49 k subset samples, a
    # partition at its ~96 ranks 1.2 ms (4× at 0.8 M samples); the ranks' values are the
    # same either way
    keys.sort()

    def value(k):
        k = k & np.uint64(0xFFFFFFFF)
        bits = np.where(k >> 31 != 0, k & np.uint64(0x7FFFFFFF), k ^ np.uint64(0xFFFFFFFF))
        return bits.astype(np.uint32).view(np.float32).astype(np.float64)

    out = np.zeros(groups)
    out[has] = (value(keys[lo]) + value(keys[hi])) / 2.0
    return out


def _group_median_mad(v: np.ndarray, g: np.ndarray, groups: int, order: tuple | None = None
                      ) -> tuple[np.ndarray, np.ndarray]:
    """Per group of ``g``: the median of ``v`` and its MAD scaled to σ (``1.4826·MAD``)."""
    order = _group_order(g, groups) if order is None else order
    med = _group_medians(v, g, groups, order)
    return med, 1.4826 * _group_medians(np.abs(v - np.take(med, g)), g, groups, order)


def _own_level(y_j: np.ndarray, y_k: np.ndarray, r: float) -> np.ndarray:
    """float64: a sample's own estimate of ``μ_k + r²·μ_j`` (what ``E[d²]`` rises with),
    ``r·(y_k + y_j)``: of the unbiased ones, that whose noise is uncorrelated with
    ``d = y_k − r·y_j`` under shot noise (var y_k = r·var y_j), where the level sets the
    noise; ``y_k + r²·y_j`` carries ``r²``× ``y_j``'s noise, against ``d``'s ``−r``×, and
    made the z-scores of its bright samples skew."""
    return r * (np.asarray(y_k, np.float64) + y_j)


#: Samples of the even subset (at most, evenly spread) that :func:`_noise_curve` fits.
CURVE_SAMPLES = 12288


def _noise_curve(e: np.ndarray, q: np.ndarray, g: np.ndarray, groups: int,
                 sig: np.ndarray, bands: int) -> tuple[float, float]:
    """``(a, c)`` of ``σ²(q) ≈ a·max(q, 0) + c``: the noise of ``d`` at a sample's own level
    ``q`` (:func:`_own_level`), from the even subset (``e``: each sample's ``d`` about its
    group's median, ``g`` its group, ``sig`` the groups' MAD σ).

    The photon-transfer line itself, fitted to the subset's groups (mean ``e²`` against
    mean ``q``; weights: relative errors alike) twice: first clipped at 5 MAD σ of each
    group — too tight for a group that mixes levels, the line comes out up to 30 % flat
    — then at 5σ of that line at each sample's own level. Grouping stays by the
    instrument: binned by their own ``q`` the samples' spreads are those of the selection
    (even of :func:`_own_level`, whose noise is independent of ``d``'s only where shot
    noise dominates; ``y_k + r²·y_j`` held 20× the noise in its outer bins). It only
    scales the clip and the z-scores. A flat line (``a = 0``) where the fit finds no rise.
    """
    # two numbers: :data:`CURVE_SAMPLES` of the subset are plenty (a step coprime with
    # the bands, as the subset's own, so that every band is among them)
    step = _stride(e.size, CURVE_SAMPLES, bands)
    e, q, g = e[::step], q[::step], g[::step]
    keep = np.abs(e) <= 5.0 * np.take(sig, g)
    a, c = 0.0, 1.0
    for _ in range(2):
        n = np.bincount(g[keep], minlength=groups)
        ok = n >= 16
        if not ok.any():
            break
        with np.errstate(over="ignore", invalid="ignore"):
            s2 = np.bincount(g[keep], weights=e[keep] ** 2, minlength=groups)[ok] / n[ok]
            qm = np.bincount(g[keep], weights=q[keep], minlength=groups)[ok] / n[ok]
        # a group whose variance overflows float64 (a diverged response curve linearised
        # the data to ~1e160 and beyond) has no usable noise; if every group does, no
        # line can be fitted: say so instead of dividing by a zero sum of weights
        fin = np.isfinite(s2) & np.isfinite(qm)
        if not fin.any():
            from mehs.errors import InputError

            raise InputError("the variance of the linearised signal overflows in every "
                             "signal group: the response curve (or the data) maps levels "
                             "to non-finite or astronomically large values")
        s2, qm = s2[fin], qm[fin]
        if not np.any(s2 > 0):
            break
        s2f = np.maximum(s2, s2[s2 > 0].min())
        # weights 1/s2f², relative to the smallest: no underflow to a zero sum (1/1e160²)
        flat = float(np.average(s2f, weights=(s2f.min() / s2f) ** 2))
        a, c = 0.0, flat
        if qm.size >= 2 and np.ptp(qm) > 0:
            A = np.stack([np.maximum(qm, 0.0), np.ones(qm.size)], axis=1) / s2f[:, None]
            (fa, fc), *_ = np.linalg.lstsq(A, np.ones(qm.size), rcond=None)
            if np.isfinite(fa) and np.isfinite(fc) and fa > 0:
                # a negative intercept (read noise below the fit's resolution): the least
                a, c = float(fa), float(fc) if fc > 0 else float(s2f.min())
        keep = e * e <= 25.0 * (a * np.maximum(q, 0.0) + c)
    return a, c


def _group_clip(e: np.ndarray, q: np.ndarray, g: np.ndarray, groups: int, a: float,
                c: float, sd: np.ndarray | None = None, order: tuple | None = None
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per group of ``g``: ``madz``, the scaled MAD of ``z = e/σ(q)`` (``σ² = a·max(q, 0)
    + c``, :func:`_noise_curve`; ≈ 1 where the line holds), and the largest own level
    ``q`` among its samples within 5 of those σ (−inf for none); per sample whether it
    lies beyond them (``far``). ``sd``: :func:`_noise_sd` of ``q``, ``order``:
    :func:`_group_order` of ``g``, when at hand.

    A MAD, not an r.m.s. within the clip: a moving patch's samples inside it spread that
    by 8 % (51 bands, the simulator's window). The level is an inlier's: a moving
    object's samples, far beyond the noise at their own bright level, set the clip ×10
    too loose for a group of three bands."""
    z = e / (_noise_sd(q, a, c) if sd is None else sd)
    madz = 1.4826 * _group_medians(np.abs(z), g, groups, order)
    mg = np.take(madz, g)
    far = (np.abs(z) > 5.0 * mg) & (mg > 0)         # a group without a spread: none
    qmax = np.full(groups, -np.inf)
    np.maximum.at(qmax, g[~far], q[~far])
    return madz, qmax, far


def _noise_sd(q: np.ndarray, a: float, c: float) -> np.ndarray:
    """float64: the noise σ of ``d`` at own levels ``q``, ``√(a·max(q, 0) + c)``
    (:func:`_noise_curve`)."""
    return np.sqrt(a * np.maximum(q, 0.0) + c)


def _clip_sigma(sig: np.ndarray, madz: np.ndarray, qmax: np.ndarray, a: float,
                c: float) -> np.ndarray:
    """float64 (groups,): the σ whose 5-fold is each group's clip — the noise σ at its
    brightest sample's own level (:func:`_group_clip`), never below the group's MAD σ
    ``sig``."""
    top = np.sqrt(a * np.maximum(np.where(np.isfinite(qmax), qmax, 0.0), 0.0) + c)
    return np.maximum(sig, madz * top)


#: Runs of pixels passed one by one to the compiled pass; more are copied together.
MAX_RUNS = 64


def _pass_split(kernel: Callable, arrays: tuple, keep: np.ndarray, rest: tuple,
                counted: tuple) -> None:
    """``kernel(*arrays, *rest)`` over the pixels (rows) ``keep``, and ``kernel(*arrays,
    *counted)`` (a clip that passes nothing: only the counts) over the others.

    The compiled pass adds to its sums in sample order, so passing it the runs of pixels
    one after another gives the bits of one pass over the kept ones, without copying
    megabytes of samples (whose fresh pages cost more than the pass); numpy's pass adds
    each call's sums at once, so it (and a scatter of many runs) gets them copied."""
    from mehs.synthesis import _ptc_numpy

    edges = np.flatnonzero(np.diff(np.concatenate(([False], keep, [False])).astype(np.int8)))
    if kernel is _ptc_numpy.ptc_pass or edges.size > 2 * MAX_RUNS:
        kernel(*(np.ascontiguousarray(a[keep]) for a in arrays), *rest)
        kernel(*(np.ascontiguousarray(a[~keep]) for a in arrays), *counted)
        return
    bounds = np.concatenate(([0], edges, [keep.size]))
    for i, (a, b) in enumerate(zip(bounds[:-1], bounds[1:])):
        if b > a:                   # runs alternate: dropped, kept, dropped, …
            kernel(*(x[a:b] for x in arrays), *(rest if i % 2 else counted))


def build_kernels_in_background() -> bool:
    """Where the photon-transfer kernels' machine code is not stored yet (a first-ever
    run), start compiling it in child processes (:func:`mehs.synthesis._native.
    build_in_background`); True if one was started. Meanwhile :func:`_kernel` gives
    numpy's: the children's entries are for the next process."""
    from mehs.synthesis import _native

    started = [_native.build_in_background(kind, np.float32) for kind in _KINDS]
    return any(started)


#: The stored photon-transfer kernels (:mod:`mehs.synthesis._ptc_kernels`).
_KINDS = ("ptc_pass", "ptc_subset")


def _kernel(dtype: np.dtype, kind: str = "ptc_pass") -> Callable:
    """:func:`mehs.synthesis._ptc_kernels.ptc_pass` (or ``kind``'s kernel there) for
    linearised samples of ``dtype``: its stored machine code (:mod:`mehs.synthesis.
    _native`: no numba start-up in a warm ``mehs fuse``), else numba's dispatcher; while
    a child process compiles that entry (a first-ever run), the same kernel in numpy
    (:mod:`mehs.synthesis._ptc_numpy`, same bits, tens of ms a pair), which beats
    waiting 3–5 s for the child."""
    from mehs.synthesis import _native

    if _native.building(kind, dtype):
        from mehs.synthesis import _ptc_numpy

        return getattr(_ptc_numpy, kind)
    entry = _native.native_kernel(kind, dtype)
    if entry is None:
        from mehs.synthesis import _ptc_kernels

        return getattr(_ptc_kernels, kind)
    return entry


def group_statistics(y_j: np.ndarray, y_k: np.ndarray, raw_j: np.ndarray, raw_k: np.ndarray,
                     saturation: np.ndarray, r: float, groups: int) -> dict[str, np.ndarray] | None:
    """Per-group robust statistics of ``d = y_k − r·y_j`` for two exposures ``j < k``.

    ``y_j``, ``y_k`` (n, bands) linearised samples (both float32, or both float64),
    ``raw_j``, ``raw_k`` their raw DN (float32), ``saturation`` (bands,) raw DN, ``r`` the
    exposure ratio. Returns per group ``n`` (samples kept), ``var``, ``mean_d``, the
    means ``yj``, ``yk``, ``q = yk + r²·yj`` and ``r``; None without a usable sample.
    """
    if not 1 <= groups < 2 ** 16:
        raise ValueError(f"groups must lie in 1 … 65535, got {groups}")
    n, nb = y_j.shape
    if nb < 2:
        return None
    if n * nb >= 2 ** 31:
        raise ValueError(f"{n} probed pixels x {nb} bands: too many samples for the "
                         "photon-transfer statistics (probe fewer pixels)")
    # each sample's instrument (the neighbouring band's y_j + y_k: independent noise)
    # as a cell of its float32 value, and whether it is saturated in either exposure or
    # in the instrument's longer one; the groups (quantiles of the instrument) and each
    # group's median and MAD, which set the clip, from an even subset of the samples
    # (the unsaturated ones of every step-th, gathered by one compiled loop)
    from mehs.synthesis._ptc_numpy import cells_flags

    nbr = _instrument(y_j).astype(np.int64)
    rj, rk = np.ascontiguousarray(raw_j), np.ascontiguousarray(raw_k)
    sat = np.ascontiguousarray(saturation, dtype=np.float32)
    step = _stride(n * nb, groups * CLIP_SAMPLES, nb)
    m = -(-(n * nb) // step)
    good, ds, q_s, pix_s = (np.empty(m, np.int32), np.empty(m), np.empty(m),
                            np.empty(m, np.int64))
    count = np.zeros(1, np.int64)
    _kernel(y_j.dtype, "ptc_subset")(y_j, y_k, rj, rk, sat, nbr, CELL_BITS, step, r,
                                      good, ds, q_s, pix_s, count)
    k = int(count[0])
    if k == 0:
        return None
    good, ds, q_s, pix_s = good[:k], ds[:k], q_s[:k], pix_s[:k]
    lo, table = _cell_groups(good, groups)
    # robust centre and spread per group (median, MAD): samples beyond 5σ — a
    # moving object, a hot pixel — are dropped; for Gaussian noise that loses
    # < 2e-5 of the variance, and symmetric trimming leaves the mean unbiased
    g_s = np.take(table, good - lo)
    order = _group_order(g_s, groups)
    med, sig = _group_median_mad(ds, g_s, groups, order)
    # The clip's σ. A group (one range of the instrument) can hold samples of very
    # different own levels — few, widely spaced bands, whose neighbour follows another
    # part of the spectrum (a sodium line beside its dark surround) — and so noise of
    # very different σ: its MAD is the dim majority's, and 5 of it cut into the bright
    # samples' noise (the gain came out 13–31 % low with 3–17 bands). So each sample's
    # deviation is measured in units of the noise at its own level (the photon-transfer
    # line of the subset, :func:`_noise_curve`) and the clip is 5 of those at the group's
    # brightest sample: for noise that is flat, or the same across a group, as before.
    e_s = ds - np.take(med, g_s)
    a, c = _noise_curve(e_s, q_s, g_s, groups, sig, nb)
    sd_s = _noise_sd(q_s, a, c)
    madz, qmax, far = _group_clip(e_s, q_s, g_s, groups, a, c, sd_s, order)
    far_pix = pix_s[far]                     # pixels with a sample beyond it (below)
    # A group without a sample in the subset is left out: it spans no cell or only
    # cells between tied values (integer levels of a dark scene), where the whole probe
    # holds about `step` times fewer samples than a statistic needs (min_group)
    picked = np.bincount(g_s, minlength=groups)
    small = (picked > 0) & (picked < CLIP_SAMPLES // 2)
    if step > 1 and small.any():    # a group short in the subset: all its samples (rare)
        cells, bad = cells_flags(y_j, y_k, rj, rk, sat, nbr, CELL_BITS)
        gid = np.take(table, np.clip(cells.ravel() - lo, 0, table.size - 1))
        sel = ~bad.ravel() & np.take(small, gid)
        ya, yb = y_j.ravel()[sel], y_k.ravel()[sel]
        dv, qv = yb - r * ya, _own_level(ya, yb, r)
        med_s, sig_s = _group_median_mad(dv, gid[sel], groups)
        madz_s, qmax_s, far_s = _group_clip(dv - np.take(med_s, gid[sel]), qv, gid[sel],
                                            groups, a, c)
        med, sig = np.where(small, med_s, med), np.where(small, sig_s, sig)
        madz, qmax = np.where(small, madz_s, madz), np.where(small, qmax_s, qmax)
        far_pix = np.concatenate((far_pix[~np.take(small, g_s[far])],
                                  np.flatnonzero(sel)[far_s] // nb))
        e_s = ds - np.take(med, g_s)            # about the short groups' new medians
    # pixels that a moving object changed between the exposures leave the statistics
    # whole: the 5σ clip kept those of its samples within 5σ, whose spread added to
    # the noise's at the levels it crossed (the gain came out ×1.4–2.3)
    moving = _moving_pixels(y_j, y_k, r, rj, rk, sat, nbr, table, lo, med, (madz, a, c),
                            (picked > 0) & (madz > 0), step > 1, pix_s, e_s, g_s, sd_s)
    # and those with a sample beyond 5σ of the noise at its own level: the clip of the
    # pass is one per group, set by its brightest inlier, and let a dim sample's outlier
    # (a moving object's, across few bands the score above cannot see) through. Where
    # the subset is every sample (few bands) this is the clip per sample; static noise
    # leaves ~6e-7 of samples out there, with their pixels
    if far_pix.size:
        moving = np.zeros(n, bool) if moving is None else moving.copy()
        moving[far_pix] = True
    # every sample: the sums about each group's median (one pass, no cancellation) and
    # each group's counts of all and of saturated samples
    nall, nbad, nt, se, se2, syj = (np.zeros(groups) for _ in range(6))
    rows = (np.empty(nb, np.int32), np.empty(nb, np.int32), np.empty(nb, np.uint8),
            np.empty(nb, np.uint8))                  # the kernel's scratch
    lim = np.where(picked > 0, 5.0 * np.maximum(_clip_sigma(sig, madz, qmax, a, c), 1e-9),
                   -1.0)
    kernel = _kernel(y_j.dtype)
    head, sums = (sat, nbr, CELL_BITS, *rows, r, lo, table, med), (nall, nbad, nt, se, se2, syj)
    if moving is None:
        kernel(y_j, y_k, rj, rk, *head, lim, *sums)
    else:
        # the moving pixels' samples still count towards their groups' saturated
        # fraction: the groups dropped for saturation stay those of every sample
        _pass_split(kernel, (y_j, y_k, rj, rk), ~moving, (*head, lim, *sums),
                    (*head, np.full(groups, -1.0), *sums))
    # a group with more than 0.1 % saturated samples is dropped whole (dropping
    # only the saturated samples would select on their own noise)
    drop = nbad > 1e-3 * np.maximum(nall, 1)
    for a in (nt, se, se2, syj):
        a[drop] = 0.0
    den = np.maximum(nt, 1)
    mean_e = se / den
    var = np.maximum(se2 / den - mean_e ** 2, 0.0)
    mean_d = np.where(nt > 0, med + mean_e, 0.0)
    yj = syj / den
    yk = np.where(nt > 0, mean_d + r * yj, 0.0)         # d = y_k − r·y_j
    return {"n": nt, "nt": nt, "var": var, "mean_d": mean_d, "q": yk + r * r * yj,
            "yj": yj, "yk": yk, "r": r}
