"""The photon-transfer group statistics as whole-array numpy steps: the formulation
:mod:`mehs.synthesis._ptc_kernels` replaced, kept as the reference its numbers must equal."""

from __future__ import annotations

import numpy as np

CELL_BITS = 18
NCELLS = 1 << CELL_BITS


def cells_of(x: np.ndarray) -> np.ndarray:
    """The cell of each float32 value: the top CELL_BITS bits of an int32 key that sorts
    like the values (−0.0 and +0.0 alike)."""
    b = np.ascontiguousarray(x, dtype=np.float32).view(np.int32)
    m = b >> 31
    key = ((b & np.int32(0x7FFFFFFF)) ^ m) - m
    return (key >> (32 - CELL_BITS)) + (NCELLS >> 1)


def group_of_cells(cells_subset, groups):
    """Quantile groups of the subset's cells: ``(lo, ends)``; a cell ``c`` is in group
    ``#(ends <= clip(c - lo))`` (cells outside the subset's span clamp to its ends)."""
    lo = int(cells_subset.min())
    counts = np.bincount(cells_subset - lo)
    cum = np.cumsum(counts)
    n = int(cum[-1])
    target = np.arange(1, groups) * (n / groups)
    last = np.searchsorted(cum, target)
    before = np.where(last > 0, cum[np.maximum(last - 1, 0)], 0)
    last = np.where(target - before < cum[last] - target, last - 1, last)
    return lo, counts.size, last + 1


def pair_groups(probe, linearise, j, k, groups, clip_samples=None):
    """numpy's statistics of exposures j < k, step for step: groups from the quantiles of
    an even subset's instrument cells, the clip's median and MAD per group from that
    subset (one ``np.median`` call each, of the float32-rounded values, as mehs defines
    them; all of a group's samples when the subset holds few, none when it holds none),
    the clipped sums over every sample, groups with > 0.1 % saturated samples dropped."""
    import math

    from mehs.synthesis._ptc_groups import CLIP_SAMPLES

    clip_samples = CLIP_SAMPLES if clip_samples is None else clip_samples
    raw_j, raw_k = probe.raw[j], probe.raw[k]
    # the dark of each sample's column, written out per sample
    reps = raw_j.shape[0] // probe.dark[j].shape[0]
    y_j = linearise(raw_j, np.tile(probe.dark[j], (reps, 1)), j)
    y_k = linearise(raw_k, np.tile(probe.dark[k], (reps, 1)), k)
    r = probe.times_ms[k] / probe.times_ms[j]
    nb = y_j.shape[-1]
    nbr = np.arange(nb) ^ 1
    nbr[nbr >= nb] = nb - 2
    inst = np.take(y_j + y_k, nbr, axis=1).ravel()
    sat = probe.saturation[None, :]
    sat_k = raw_k >= sat
    badf = (sat_k | (raw_j >= sat) | np.take(sat_k, nbr, axis=1)).ravel()
    d = (y_k - r * y_j).ravel()
    c = cells_of(inst)
    step = max(1, d.size // (groups * clip_samples))
    while step > 1 and math.gcd(step, nb) != 1:
        step += 1
    sub = np.zeros(d.size, bool)
    sub[::step] = True
    good_sub = sub & ~badf
    if not good_sub.any():
        return None
    lo, m, ends = group_of_cells(c[good_sub], groups)
    gid = np.searchsorted(ends, np.clip(c - lo, 0, m - 1), side="right")
    med = np.zeros(groups)
    sig = np.zeros(groups)
    picked = np.bincount(gid[good_sub], minlength=groups)
    for gi in range(groups):
        if step > 1 and 0 < picked[gi] < clip_samples // 2:
            dv = d[~badf & (gid == gi)]
        else:
            dv = d[good_sub & (gid == gi)]
        if dv.size == 0:
            continue
        med[gi] = np.median(dv.astype(np.float32).astype(np.float64))
        sig[gi] = 1.4826 * np.median(np.abs(dv - med[gi]).astype(np.float32).astype(np.float64))
    nall = np.bincount(gid, minlength=groups)
    nbad = np.bincount(gid[badf], minlength=groups)
    keep = nbad <= 1e-3 * np.maximum(nall, 1)
    e = d - np.take(med, gid)
    lim = np.where(picked > 0, 5.0 * np.maximum(sig, 1e-9), -1.0)   # none in the subset: out
    t = (np.abs(e) <= np.take(lim, gid)) & ~badf & np.take(keep, gid)
    gt, et = gid[t], e[t]
    nt = np.bincount(gt, minlength=groups).astype(np.float64)
    den = np.maximum(nt, 1)
    mean_e = np.bincount(gt, weights=et, minlength=groups) / den
    var = np.maximum(np.bincount(gt, weights=et * et, minlength=groups) / den - mean_e ** 2, 0.0)
    mean_d = np.where(nt > 0, med + mean_e, 0.0)
    yj = np.bincount(gt, weights=y_j.ravel()[t], minlength=groups) / den
    yk = np.where(nt > 0, mean_d + r * yj, 0.0)
    return {"n": nt, "nt": nt, "var": var, "mean_d": mean_d, "q": yk + r * r * yj,
            "yj": yj, "yk": yk, "r": r}
