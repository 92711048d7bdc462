"""Noise model and linearity measured from the bracket itself (photon transfer across exposures).

A Specim IQ folder stores its dark reference as one averaged line, so the
temporal noise cannot be read off the dark frames; the exposures of a
static scene measure it instead. For two exposures ``j < k`` (ratio
``r = t_k/t_j``) of the same pixel and band, ``d = y_k − r·y_j`` has mean 0
when the sensor is linear and variance ::

    E[d²] = gain·(μ_k + r²·μ_j) + a_k + r²·a_j,   a_j = σ² + gain·D·t_j

(``μ`` the mean signal, ``σ²`` the zero-signal variance: read noise,
quantisation, the dark reference's error; ``D`` the dark current in DN/ms,
whose electrons add shot noise though their mean is subtracted). Since
``E[y_k + r²·y_j] = μ_k + r²·μ_j`` the relation also holds for group means,
provided the groups are chosen **independently of the noise** of that
pixel and band — otherwise conditioning on a noisy value shrinks the
variance (selection bias). The groups here are quantiles of an
*instrument*: the same pixel's signal in the neighbouring band, which
follows the same radiance but carries independent noise. A linear
least-squares fit over groups and exposure pairs gives ``gain`` and ``σ²``;
``D`` comes from the dark references' growth with time.

The same groups measure linearity: ``Σ y_k / (r·Σ y_j)`` per signal level
is 1 at every level for a linear sensor with correct exposure times.

References
----------
- EMVA Standard 1288, release 4.0 (2021): photon transfer method.
- Janesick, J. R. (2007). *Photon Transfer: DN → λ*. SPIE Press.
- Hasinoff, S. W., Durand, F. and Freeman, W. T. (2010). Noise-optimal capture
  for high dynamic range photography. CVPR.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, Callable

import numpy as np

from mehs.errors import InputError
from mehs.synthesis.merge import NoiseModel

#: Instrument-quantile groups per exposure pair.
PTC_GROUPS = 48

#: Pixels (whole lines, evenly spaced) read for the photon-transfer statistics: 0.8
#: million samples a pair at 204 bands. Measured on the simulator's scenes (512², four
#: kinds, brackets ×8 and ×30 apart, three seeds each): the noise model's gain within
#: 0.1–4.9 % of the sensor's (8192 pixels: 0.6–3.6 %; the error is mostly the method's
#: bias, not sampling), the linearity test's resolution 0.3–0.8 % against its 2 %
#: tolerance (8192: 0.2–0.5 %). Half the pixels of before, so that the test costs under
#: a fifth of a 512² merge (issue 16).
PROBE_PIXELS = 4096
#: The probe of a linearity test whose first answer was not clear-cut
#: (:func:`mehs.synthesis.fuse_response.linearity_auto`).
PROBE_PIXELS_FINE = 16384


@dataclass
class ProbeSamples:
    """Raw samples of a subset of whole lines of a bracket.

    Attributes
    ----------
    raw
        float32 ``(P, n, bands)`` raw DN (n = probed pixels, whole lines one after another).
    dark
        float32 ``(P, samples, bands)`` the dark level of each column of the probed lines
        (0 if none), or ``(P, n, bands)``: one per sample.
    times_ms
        float64 ``(P,)`` ascending.
    saturation
        float32 ``(bands,)`` raw DN saturation levels.
    """

    raw: np.ndarray
    dark: np.ndarray
    times_ms: np.ndarray
    saturation: np.ndarray
    lines: np.ndarray = field(default_factory=lambda: np.zeros(0, int))
    cache: dict = field(default_factory=dict, repr=False)

    def linearised(self, linearise: Callable, j: int) -> np.ndarray:
        """``linearise(raw, dark, j)`` of exposure ``j``, ``(n, bands)``: the lines' raw
        samples against the dark's columns, broadcast (never materialised per sample)."""
        raw, dark = self.raw[j], self.dark[j]
        if dark.shape[0] == raw.shape[0]:
            return np.asarray(linearise(raw, dark, j))
        y = np.asarray(linearise(raw.reshape(-1, *dark.shape), dark, j))
        return y.reshape(raw.shape)


def probe_bracket(bracket, saturation: np.ndarray,
                  max_pixels: int = PROBE_PIXELS) -> ProbeSamples:
    """Read evenly spaced whole lines (contiguous reads of a memmap) of every exposure."""
    nl, ns, nb = bracket.shape
    step = max(1, int(np.ceil(nl * ns / max_pixels)))
    lines = np.arange(step // 2, nl, step)
    P = len(bracket.exposures)
    raw = np.empty((P, lines.size * ns, nb), dtype=np.float32)
    dark = np.zeros((P, ns, nb), dtype=np.float32)       # per column: a line's darks

    def read(j0: int, j1: int) -> None:
        for j in range(j0, j1):
            a = np.asarray(bracket.exposures[j].data)
            bil = a.transpose(0, 2, 1)
            # a BIL file (Specim's): gather whole lines as stored, transpose them in memory
            block = bil[lines].transpose(0, 2, 1) if bil.flags.c_contiguous else a[lines]
            raw[j].reshape(lines.size, ns, nb)[...] = block
            if bracket.darks[j] is not None:
                dark[j] = bracket.darks[j]

    from mehs.synthesis._ranges import run_ranges

    # the exposures on threads: numpy's gather and converting copy release the GIL
    run_ranges(P, read, max_step=1, name="mehs-probe")
    return ProbeSamples(raw, dark, np.asarray(bracket.times_ms, dtype=np.float64),
                        np.broadcast_to(np.asarray(saturation, np.float32), (nb,)).copy(), lines)


def _trim_mean(a: np.ndarray, cut: float) -> float:
    """``scipy.stats.trim_mean(a, cut)`` of a 1-D array by partition, not a full sort.

    Drops ``int(cut·n)`` values at each end, as scipy does; importing scipy.stats
    for this one call cost 0.8 s of every ``mehs fuse`` (issue 16).
    """
    n = a.size
    lo = int(cut * n)
    hi = n - lo
    if lo >= hi:
        raise ValueError(f"trimming {cut} of {n} values leaves none")
    if lo == 0:
        return float(a.mean())
    part = np.partition(a, (lo, hi - 1))
    return float(part[lo:hi].mean())


def dark_current_from_darks(darks, times_ms) -> float:
    """Dark current (DN/ms) from the growth of the median dark level with time; 0 if unknown."""
    t = np.asarray(times_ms, dtype=np.float64)
    if len(darks) < 2 or any(d is None for d in darks):
        return 0.0
    # a trimmed mean, not the median: stored darks are rounded to whole DN, and
    # the median of rounded differences is itself a whole number
    med = np.array([_trim_mean((np.asarray(d, dtype=np.float64) - darks[0]).ravel(), 0.1)
                    for d in darks])
    dt = t - t[0]
    if not np.any(dt > 0):
        return 0.0
    slope = float(np.dot(dt, med) / np.dot(dt, dt))
    return max(slope, 0.0) if np.isfinite(slope) else 0.0


def _instrument(y: np.ndarray) -> np.ndarray:
    """The neighbouring band of each band (b ↔ b ^ 1; the last odd one out uses b − 1)."""
    nb = y.shape[-1]
    idx = np.arange(nb) ^ 1
    idx[idx >= nb] = nb - 2 if nb >= 2 else 0
    return idx


def _consecutive_pairs(probe: ProbeSamples, linearise: Callable, groups: int,
                      key: str | None) -> None:
    """Compute the statistics of every pair ``(j, j + 1)`` not yet kept under ``key``,
    the pairs side by side on threads (their kernels release the GIL; each pair's
    numbers are the same as computed alone)."""
    if key is None:
        return
    P = probe.raw.shape[0]
    todo = [j for j in range(P - 1) if (key, j, j + 1, groups) not in probe.cache]
    from mehs.synthesis._ranges import thread_count

    nthreads = min(len(todo), thread_count())
    if nthreads < 2:
        return
    from concurrent.futures import ThreadPoolExecutor

    with ThreadPoolExecutor(nthreads, thread_name_prefix="mehs-ptc") as pool:
        # each exposure linearised once (numpy releases the GIL), then the pairs
        for f in [pool.submit(_linearised, probe, linearise, j, key)
                  for j in sorted({j for i in todo for j in (i, i + 1)})]:
            f.result()
        for f in [pool.submit(_pair_groups, probe, linearise, j, j + 1, groups, key)
                  for j in todo]:
            f.result()


def _pair_groups(probe: ProbeSamples, linearise: Callable, j: int, k: int,
                 groups: int, key: str | None = None) -> dict[str, np.ndarray] | None:
    """Per-group robust statistics for exposures j < k (cached under ``key`` when given)."""
    if key is not None and (key, j, k, groups) in probe.cache:
        return probe.cache[(key, j, k, groups)]
    out = _pair_groups_compute(probe, linearise, j, k, groups, key)
    if key is not None:
        probe.cache[(key, j, k, groups)] = out
    return out


#: Bits of the float32 order key that name a cell of :func:`_group_table`.
CELL_BITS = 18


def _group_bounds(good: np.ndarray, groups: int) -> np.ndarray | None:
    """The groups of a run of consecutive cells of the instrument's value
    (:func:`mehs.synthesis._ptc_kernels._row_cells`), from the number of good samples in
    each (``good``: every cell from the lowest to the highest one in use): int64
    ``(groups + 1,)`` bounds, group ``k`` the cells ``bounds[k] … bounds[k + 1] − 1``
    (possibly none); None without good samples.

    Groups are ranges of the instrument holding about equal numbers of good samples,
    bounded at the cell edges nearest to the quantiles ``k/groups``: a sample's group is
    a table lookup of its cell (:func:`_group_table`) — neither a partition for the
    quantiles nor a binary search per value. Like quantile edges they depend on the
    instrument only; a cell's worth of tied values (one integer level of a dark scene)
    stays in one group, as equal quantiles would leave it.
    """
    cum = np.cumsum(good)                        # good samples in cells up to each
    n = int(cum[-1])
    if n == 0:
        return None
    target = np.arange(1, groups) * (n / groups)
    last = np.searchsorted(cum, target)          # the cell holding each target rank
    before = np.where(last > 0, cum[np.maximum(last - 1, 0)], 0)
    # the group ends after that cell, or before it when that is nearer the target
    # (non-decreasing: a later target moves the end no earlier)
    last = np.where(target - before < cum[last] - target, last - 1, last)
    return np.concatenate(([0], last + 1, [good.size])).astype(np.int64)


def _group_table(good: np.ndarray, groups: int) -> np.ndarray | None:
    """uint16: the group (0 … ``groups − 1``) of each cell (see :func:`_group_bounds`)."""
    bounds = _group_bounds(good, groups)
    if bounds is None:
        return None
    return np.repeat(np.arange(groups, dtype=np.uint16), np.diff(bounds))


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
    """uint64 keys (below 2**32) of float32-rounded ``x`` that sort like the values."""
    b = np.ascontiguousarray(x, dtype=np.float32).view(np.uint32).astype(np.uint64)
    return np.where(b >> 31 != 0, b ^ np.uint64(0xFFFFFFFF), b | np.uint64(0x80000000))


def _group_medians(v: np.ndarray, g: np.ndarray, groups: int) -> np.ndarray:
    """float64 (groups,) the median of the float32-rounded ``v`` of each group ``g`` (0 for
    an empty group), as ``np.median`` defines it (the mean of the two middle values of
    an even count), from one selection among ``group << 32 | value key``: no Python loop
    over the groups, and the selection releases the GIL, so that the exposure pairs'
    statistics run side by side on threads (a loop of ``np.median`` calls held it for
    3–7 ms a pair, issue 16)."""
    keys = (g.astype(np.uint64) << np.uint64(32)) | _order_keys(v)
    count = np.bincount(g, minlength=groups)
    start = np.cumsum(count) - count
    has = count > 0
    lo, hi = (start + (count - 1) // 2)[has], (start + count // 2)[has]
    if keys.size:
        # the keys order by group, then value: each group's middle ranks are the same
        # positions of the whole, so one selection finds them all
        keys.partition(np.union1d(lo, hi))

    def value(k):
        k = k & np.uint64(0xFFFFFFFF)
        bits = np.where(k >> 31 != 0, k & np.uint64(0x7FFFFFFF), k ^ np.uint64(0xFFFFFFFF))
        return bits.astype(np.uint32).view(np.float32).astype(np.float64)

    out = np.zeros(groups)
    out[has] = (value(keys[lo]) + value(keys[hi])) / 2.0
    return out


def _group_median_mad(v: np.ndarray, g: np.ndarray, groups: int) -> tuple[np.ndarray, np.ndarray]:
    """Per group of ``g``: the median of ``v`` and its MAD scaled to σ (``1.4826·MAD``)."""
    med = _group_medians(v, g, groups)
    return med, 1.4826 * _group_medians(np.abs(v - np.take(med, g)), g, groups)


def _linearised(probe: ProbeSamples, linearise: Callable, j: int, key: str | None) -> np.ndarray:
    """Exposure ``j``'s linearised samples, C-contiguous (kept under ``key``: the middle
    exposures serve two pairs)."""
    if key is not None and (key, "y", j) in probe.cache:
        return probe.cache[(key, "y", j)]
    y = probe.linearised(linearise, j)
    if y.dtype not in (np.float32, np.float64):
        y = y.astype(np.float64)
    y = np.ascontiguousarray(y)
    if key is not None:
        probe.cache[(key, "y", j)] = y
    return y


def build_kernels_in_background() -> bool:
    """Where the photon-transfer passes' machine code is not stored yet (a first-ever
    run), start compiling it in a child process (:func:`mehs.synthesis._native.
    build_in_background`); True if one was started. Meanwhile :func:`_kernel` gives
    numpy's pass: the child's entry is for the next process."""
    from mehs.synthesis import _native

    return _native.build_in_background("ptc_pass", np.float32)


def _kernel(dtype: np.dtype) -> Callable:
    """:func:`mehs.synthesis._ptc_kernels.ptc_pass` for linearised samples of ``dtype``:
    its stored machine code (:mod:`mehs.synthesis._native`: no numba start-up in a warm
    ``mehs fuse``), else numba's dispatcher; while a child process compiles that entry
    (a first-ever run), the same pass in numpy (:mod:`mehs.synthesis._ptc_numpy`, same
    bits, tens of ms a pair), which beats waiting 3–5 s for the child."""
    from mehs.synthesis import _native

    if _native.building("ptc_pass", dtype):
        from mehs.synthesis._ptc_numpy import ptc_pass

        return ptc_pass
    entry = _native.native_kernel("ptc_pass", dtype)
    if entry is None:
        from mehs.synthesis._ptc_kernels import ptc_pass

        return ptc_pass
    return entry


def _pair_groups_compute(probe: ProbeSamples, linearise: Callable, j: int, k: int,
                         groups: int, key: str | None = None) -> dict[str, np.ndarray] | None:
    if not 1 <= groups < 2 ** 16:
        raise ValueError(f"groups must lie in 1 … 65535, got {groups}")
    raw_j, raw_k = probe.raw[j], probe.raw[k]
    y_j = _linearised(probe, linearise, j, key)
    y_k = _linearised(probe, linearise, k, key)
    if y_k.dtype != y_j.dtype:
        y_j, y_k = y_j.astype(np.float64), y_k.astype(np.float64)
    # float64, as the statistics are: y_k − r·y_j is formed in float64
    r = np.float64(probe.times_ms[k] / probe.times_ms[j])
    n, nb = y_j.shape
    if nb < 2:
        return None
    if n * nb >= 2 ** 31:
        raise ValueError(f"{n} probed pixels x {nb} bands: too many samples for the "
                         "photon-transfer counts (probe fewer pixels)")
    # each sample's instrument (the neighbouring band's y_j + y_k: independent noise)
    # as a cell of its float32 value, and whether it is saturated in either exposure or
    # in the instrument's longer one; the groups (quantiles of the instrument) and each
    # group's median and MAD, which set the clip, from an even subset of the samples
    from mehs.synthesis._ptc_numpy import cells_flags

    nbr = _instrument(y_j).astype(np.int64)
    rj, rk = np.ascontiguousarray(raw_j), np.ascontiguousarray(raw_k)
    sat = probe.saturation
    step = _stride(n * nb, groups * CLIP_SAMPLES, nb)
    index = np.arange(0, n * nb, step)
    cells_s, bad_s = cells_flags(y_j, y_k, rj, rk, sat, nbr, CELL_BITS, index)
    good = cells_s[~bad_s]
    if good.size == 0:
        return None
    lo = int(good.min())
    bounds = _group_bounds(np.bincount(good - lo), groups)
    table = np.repeat(np.arange(groups, dtype=np.uint16), np.diff(bounds))
    # robust centre and spread per group (median, MAD): samples beyond 5σ — a
    # moving object, a hot pixel — are dropped; for Gaussian noise that loses
    # < 2e-5 of the variance, and symmetric trimming leaves the mean unbiased
    g_s = np.take(table, good - lo)
    ds = (y_k.ravel()[index] - r * y_j.ravel()[index])[~bad_s]
    med, sig = _group_median_mad(ds, g_s, groups)
    # A group without a sample in the subset is left out: it spans no cell or only
    # cells between tied values (integer levels of a dark scene), where the whole probe
    # holds about `step` times fewer samples than a statistic needs (min_group)
    picked = np.bincount(g_s, minlength=groups)
    small = (picked > 0) & (picked < CLIP_SAMPLES // 2)
    if step > 1 and small.any():    # a group short in the subset: all its samples (rare)
        cells, bad = cells_flags(y_j, y_k, rj, rk, sat, nbr, CELL_BITS)
        gid = np.take(table, np.clip(cells.ravel() - lo, 0, table.size - 1))
        sel = ~bad.ravel() & np.take(small, gid)
        med_s, sig_s = _group_median_mad((y_k - r * y_j).ravel()[sel], gid[sel], groups)
        med, sig = np.where(small, med_s, med), np.where(small, sig_s, sig)
    # every sample: the sums about each group's median (one pass, no cancellation) and
    # each group's counts of all and of saturated samples
    nall, nbad, nt, se, se2, syj = (np.zeros(groups) for _ in range(6))
    rows = (np.empty(nb, np.int32), np.empty(nb, np.int32), np.empty(nb, np.uint8),
            np.empty(nb, np.uint8))                  # the kernel's scratch
    lim = np.where(picked > 0, 5.0 * np.maximum(sig, 1e-9), -1.0)
    _kernel(y_j.dtype)(y_j, y_k, rj, rk, sat, nbr, CELL_BITS, *rows, r, lo, table, med, lim,
                       nall, nbad, nt, se, se2, syj)
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


def estimate_noise_PTC(probe: ProbeSamples, linearise: Callable, *, dark_current: float = 0.0,
                       groups: int = PTC_GROUPS, min_group: int = 64,
                       linear: bool = True, key: str | None = None) -> tuple[NoiseModel, dict[str, Any]]:
    """Gain, zero-signal noise and relative error of a bracket's linearised samples.

    Parameters
    ----------
    probe
        Samples from :func:`probe_bracket`.
    linearise
        ``f(raw (n, bands), dark (n, bands), j) → y`` dark-subtracted linear DN (float).
    dark_current
        DN/ms (:func:`dark_current_from_darks`).
    linear
        ``False`` for a recovered curve: the relative inconsistency between
        exposures (curve error) is measured into ``NoiseModel.relative``.
    key
        Caches the group statistics in ``probe`` under this name (the same
        lineariser must always go with the same key).

    Returns
    -------
    (NoiseModel, diagnostics)

    Raises
    ------
    InputError
        When too few groups are usable or the fit is not physical.
    """
    P = probe.raw.shape[0]
    t = probe.times_ms
    _consecutive_pairs(probe, linearise, groups, key)
    rows, rhs, cnt, rel = [], [], [], []
    for j in range(P - 1):
        k = j + 1
        st = _pair_groups(probe, linearise, j, k, groups, key)
        if st is None:
            continue
        r = st["r"]
        ok = st["nt"] >= min_group
        Dj, Dk = dark_current * t[j], dark_current * t[k]
        for gi in np.flatnonzero(ok):
            # E[d²] = gain·(q + D_k + r²D_j) + σ²·(1 + r²)
            rows.append([st["q"][gi] + Dk + r * r * Dj, 1.0 + r * r])
            rhs.append(st["var"][gi])
            cnt.append(st["nt"][gi])
            if st["yk"][gi] > 0:
                rel.append((st["mean_d"][gi] / st["yk"][gi], st["n"][gi], st["var"][gi],
                            st["yk"][gi]))
    if len(rows) < 4:
        raise InputError(f"only {len(rows)} usable signal groups to measure the noise")
    A = np.asarray(rows)
    b = np.asarray(rhs)
    n = np.asarray(cnt)
    # a group's mean d² scatters by var·√(2/n): weights √n / var, with the
    # fitted variance in the second round (the measured one correlates with its error)
    w = np.sqrt(n) / np.maximum(b, 1e-12)
    for _ in range(2):
        sol, *_ = np.linalg.lstsq(A * w[:, None], b * w, rcond=None)
        w = np.sqrt(n) / np.maximum(A @ sol, 1e-12)
    gain, s2 = float(sol[0]), float(sol[1])
    if not (np.isfinite(gain) and gain > 0):
        raise InputError(f"photon-transfer fit gave a non-positive gain ({gain:.3g})")
    s2 = max(s2, 1.0 / 12.0)                  # at least the quantisation noise
    relative = 0.0
    if not linear and rel:
        rr = np.array(rel)
        # relative inconsistency d/y_k of well-exposed groups beyond its noise
        noise2 = rr[:, 2] / np.maximum(rr[:, 1], 1) / np.maximum(rr[:, 3], 1e-9) ** 2
        bias2 = np.maximum(rr[:, 0] ** 2 - noise2, 0.0)
        relative = float(np.sqrt(np.median(bias2) / 2.0)) if bias2.size else 0.0
    resid = (b - A @ sol) / np.maximum(A @ sol, 1e-12)
    model = NoiseModel(gain=gain, read_noise=float(np.sqrt(s2)), relative=relative,
                       dark_current=float(dark_current), source="photon transfer (bracket)")
    diag = {"groups": int(len(b)), "fit_rel_rms": float(np.sqrt(np.mean(resid ** 2)))}
    return model, diag


def linearity_PTC(probe: ProbeSamples, linearise: Callable, *, groups: int = PTC_GROUPS,
                  min_level: float = 0.02, max_level: float = 0.85,
                  bit_depth: int = 12, key: str | None = None) -> dict[str, Any]:
    """How far ``Σ y_k / (r·Σ y_j)`` strays from 1 over the signal levels (a linear sensor: ≈ 0).

    Groups (instrument quantiles, see the module docstring) whose mean longer-exposure
    level lies in ``[min_level, max_level]·(2**bit_depth − 1)`` count.

    Returns
    -------
    dict
        ``deviation``: the 75th percentile over the groups of |ratio − 1| (each
        group's ratio noise, 3 standard errors, subtracted in quadrature),
        ``deviation_max``, ``levels`` (groups counted), ``ratios`` list of (level, ratio),
        ``resolution`` (median over the groups of 3 standard errors of the ratio).
    """
    L = (1 << bit_depth) - 1
    P = probe.raw.shape[0]
    dev, ratios, res3 = [], [], []
    _consecutive_pairs(probe, linearise, groups, key)
    for j in range(P - 1):
        st = _pair_groups(probe, linearise, j, j + 1, groups, key)
        if st is None:
            continue
        ok = (st["n"] >= 64) & (st["yk"] > min_level * L) & (st["yk"] < max_level * L)
        for gi in np.flatnonzero(ok):
            ratio = 1.0 + st["mean_d"][gi] / (st["r"] * st["yj"][gi])
            # noise of the ratio: std(d)/√n relative to y_k
            se = np.sqrt(st["var"][gi] / st["n"][gi]) / st["yk"][gi]
            dev.append(np.sqrt(max((ratio - 1.0) ** 2 - (3 * se) ** 2, 0.0)))
            res3.append(3 * se)
            ratios.append((float(st["yk"][gi]), float(ratio)))
    if not dev:
        raise InputError("no well-exposed signal level seen by two exposures: linearity unknown")
    # the 75th percentile over levels, not the maximum: a moving object fills a
    # few signal levels with inconsistent exposures, a response non-linearity most
    # ``resolution``: the smallest deviation the test could have seen (median 3 s.e.);
    # brackets ×30–×150 apart on few pixels leave it far above a 2 % tolerance, and a
    # deviation of 0 then means "could not tell", not "linear"
    return {"deviation": float(np.percentile(dev, 75)), "deviation_max": float(np.max(dev)),
            "levels": len(dev), "ratios": ratios, "resolution": float(np.median(res3))}
