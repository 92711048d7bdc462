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

from dataclasses import dataclass, field
from typing import Any, Callable

import numpy as np

from mehs.errors import InputError
from mehs.synthesis._ptc_groups import group_statistics
from mehs.synthesis.merge import NoiseModel

#: Instrument-quantile groups per exposure pair.
PTC_GROUPS = 48

#: Pixels (whole lines, evenly spaced) read for the photon-transfer statistics: 0.8
#: million samples a pair at 204 bands. ``benchmarks/bench_noise_probe.py`` (512², four
#: scene kinds, brackets ×8 and ×30 apart, three seeds; the simulator's sensor the
#: truth): the noise model's gain error median 1.3 %, max 3.9 % (8192 pixels: 1.8 % /
#: 3.1 %; 16384: 1.6 % / 3.4 % — the error is the method's bias, not sampling); the
#: linearity test's resolution 0.38–0.89 % against its 2 % tolerance (8192: 0.26–0.64 %).
#: Half the pixels of before, so that the test costs under a fifth of a 512² merge
#: (issue 16).
PROBE_PIXELS = 4096
#: The probe of a linearity test whose first answer was not clear-cut
#: (:func:`mehs.synthesis.fuse_response.linearity_auto`).
PROBE_PIXELS_FINE = 16384
#: A probe holds at least its pixels × this many bands of samples: a bracket of fewer
#: bands reads more pixels. ``PROBE_PIXELS`` of 2–3 bands held 8–12 thousand samples a
#: pair (0.8 million at 204 bands): over four seeds of four 512² simulated scenes the gain
#: scattered −19 … +7 % (2 bands) and −13 … +10 % (3 bands), and the linearity test of a
#: 3-band window scene found no level at all; read to 0.13–0.2 million samples, −2 … +3 %
#: (2 bands, but for one seed of the window scene: +13 %) and −2 … +3 % (3 bands), as
#: with 17 or 51 bands. 48 keeps the probe of 51 bands (and more) as it was.
PROBE_BANDS = 48
#: … up to this many times its pixels: 2 bands read 0.13 million samples. Probe and
#: statistics of a 512² 3-band bracket take 27–48 ms (were 9–11 ms; 3–10× its merge,
#: which is 40× cheaper than at 204 bands, where nothing changes: 0.19× the merge).
PROBE_MAX_SCALE = 16


def probe_pixels(max_pixels: int, bands: int) -> int:
    """Pixels a probe of ``max_pixels`` reads of a bracket of ``bands`` bands: at least
    ``max_pixels × PROBE_BANDS`` samples, at most ``PROBE_MAX_SCALE × max_pixels``
    pixels."""
    want = -(-max_pixels * PROBE_BANDS // max(bands, 1))
    return int(min(max(max_pixels, want), max_pixels * PROBE_MAX_SCALE))


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
    integer
        Whether the raw samples are whole ADC codes (an integer cube), not floats of
        any scale (an already-linear float cube): the noise model's quantisation floor.
    """

    raw: np.ndarray
    dark: np.ndarray
    times_ms: np.ndarray
    saturation: np.ndarray
    lines: np.ndarray = field(default_factory=lambda: np.zeros(0, int))
    integer: bool = True
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
    """Read evenly spaced whole lines (contiguous reads of a memmap) of every exposure:
    ``max_pixels`` pixels of a bracket of :data:`PROBE_BANDS` bands or more, more of one
    of fewer (:func:`probe_pixels`)."""
    nl, ns, nb = bracket.shape
    step = max(1, int(np.ceil(nl * ns / probe_pixels(max_pixels, nb))))
    # at least one line: a scan shorter than half a step (a few lines of a very wide
    # sensor) started past its end, probed nothing and fell back to the default noise
    lines = np.arange(min(step // 2, nl - 1), nl, step)
    P = len(bracket.exposures)
    raw = np.empty((P, lines.size * ns, nb), dtype=np.float32)
    dark = np.zeros((P, ns, nb), dtype=np.float32)       # per column: a line's darks

    from mehs.synthesis._ranges import run_ranges, thread_count

    # each exposure's lines in as many parts as threads: three exposures on two threads
    # left one thread idle for a third of the read
    parts = max(1, min(thread_count(), lines.size))

    def read(k0: int, k1: int) -> None:
        for k in range(k0, k1):
            j, part = divmod(k, parts)
            at = slice(part * lines.size // parts, (part + 1) * lines.size // parts)
            a = np.asarray(bracket.exposures[j].data)
            bil = a.transpose(0, 2, 1)
            # a BIL file (Specim's): gather whole lines as stored, transpose them in memory
            block = (bil[lines[at]].transpose(0, 2, 1) if bil.flags.c_contiguous
                     else a[lines[at]])
            raw[j].reshape(lines.size, ns, nb)[at] = block
            if part == 0 and bracket.darks[j] is not None:
                dark[j] = bracket.darks[j]

    # on threads: numpy's gather and converting copy release the GIL
    run_ranges(P * parts, read, max_step=1, name="mehs-probe")
    integer = all(np.issubdtype(np.asarray(e.data).dtype, np.integer) for e in bracket.exposures)
    return ProbeSamples(raw, dark, np.asarray(bracket.times_ms, dtype=np.float64),
                        np.broadcast_to(np.asarray(saturation, np.float32), (nb,)).copy(), lines,
                        integer=integer)


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


def _pair_groups_compute(probe: ProbeSamples, linearise: Callable, j: int, k: int,
                         groups: int, key: str | None = None) -> dict[str, np.ndarray] | None:
    """:func:`mehs.synthesis._ptc_groups.group_statistics` of exposures j < k of the probe."""
    y_j = _linearised(probe, linearise, j, key)
    y_k = _linearised(probe, linearise, k, key)
    if y_k.dtype != y_j.dtype:
        y_j, y_k = y_j.astype(np.float64), y_k.astype(np.float64)
    # float64, as the statistics are: y_k − r·y_j is formed in float64
    r = np.float64(probe.times_ms[k] / probe.times_ms[j])
    return group_statistics(y_j, y_k, probe.raw[j], probe.raw[k], probe.saturation, r, groups)


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
    P, _, nb = probe.raw.shape
    t = probe.times_ms
    if nb < 2:
        # the groups are levels of the neighbouring band (see the module docstring): a
        # single band has none, and grouping by a sample's own level would bias the
        # variance; said as such, not as "0 usable groups"
        raise InputError("a single band cannot measure the noise: photon transfer groups "
                         "each band's samples by the signal of a neighbouring band")
    _consecutive_pairs(probe, linearise, groups, key)
    rows, rhs, cnt, rel = [], [], [], []
    why = {"exposure pair(s) without an unsaturated sample": 0, "groups saturated or empty": 0,
           f"groups of fewer than {min_group} samples": 0}
    for j in range(P - 1):
        k = j + 1
        st = _pair_groups(probe, linearise, j, k, groups, key)
        if st is None:
            why["exposure pair(s) without an unsaturated sample"] += 1
            continue
        r = st["r"]
        ok = st["nt"] >= min_group
        why["groups saturated or empty"] += int(np.count_nonzero(st["nt"] == 0))
        why[f"groups of fewer than {min_group} samples"] += int(np.count_nonzero(
            (st["nt"] > 0) & ~ok))
        Dj, Dk = dark_current * t[j], dark_current * t[k]
        # each group's variance about its own mean, made unbiased (n − 1): the n-divided
        # one is (n − 1)/n of it, 1.5 % low for the smallest groups of few bands
        var = st["var"] * st["nt"] / np.maximum(st["nt"] - 1.0, 1.0)
        for gi in np.flatnonzero(ok):
            # E[d²] = gain·(q + D_k + r²D_j) + σ²·(1 + r²)
            rows.append([st["q"][gi] + Dk + r * r * Dj, 1.0 + r * r])
            rhs.append(var[gi])
            cnt.append(st["nt"][gi])
            if st["yk"][gi] > 0:
                rel.append((st["mean_d"][gi] / st["yk"][gi], st["n"][gi], st["var"][gi],
                            st["yk"][gi]))
    if len(rows) < 4:
        # which of the reasons left the groups out: every level saturated in the
        # longer exposure, or too few samples (a tiny or dark bracket)
        detail = ", ".join(f"{v} {k}" for k, v in why.items() if v)
        raise InputError(f"only {len(rows)} usable signal groups to measure the noise: "
                         f"{detail or 'no group'} (of {P - 1} exposure pair(s), {groups} "
                         "groups each)")
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
    # at least the quantisation noise: of whole ADC codes (1/12 DN²); a float cube's
    # scale is its own (radiance-like units: σ² far below 1/12, and that floor made its
    # read noise ×14 and flagged 30 % of a static scene as ghosts), so there at least
    # the rounding of whole electrons (gain²/12)
    s2 = max(s2, 1.0 / 12.0 if probe.integer else gain * gain / 12.0)
    relative = 0.0
    if not linear and rel:
        rr = np.array(rel)
        # relative inconsistency d/y_k of well-exposed groups beyond its noise. The
        # curve errs by different amounts at different levels: the median left half the
        # levels' error out of the χ² weights, and with a gain measured right (not inflated
        # by a moving object) 139 static pixels of a gamma sensor's bracket passed for
        # ghosts; the upper quartile covers them (none; the moving patch still found)
        noise2 = rr[:, 2] / np.maximum(rr[:, 1], 1) / np.maximum(rr[:, 3], 1e-9) ** 2
        bias2 = np.maximum(rr[:, 0] ** 2 - noise2, 0.0)
        relative = float(np.sqrt(np.percentile(bias2, 75) / 2.0)) if bias2.size else 0.0
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
    level lies in ``[min_level, max_level]·(2**bit_depth − 1)`` count; for a float cube
    (``probe.integer`` False), whose scale the bit depth does not give, of its largest
    saturation level where that is lower.

    Returns
    -------
    dict
        ``deviation``: the 75th percentile over the groups of |ratio − 1| (each
        group's ratio noise, 3 standard errors, subtracted in quadrature),
        ``deviation_max``, ``levels`` (groups counted), ``ratios`` list of (level, ratio),
        ``resolution`` (median over the groups of 3 standard errors of the ratio).
    """
    L = (1 << bit_depth) - 1
    if not probe.integer:
        # a float cube in radiance-like units (a few units at most) has no level within
        # 2–85 % of 4095: "linearity unknown" for every such bracket
        L = min(L, float(np.max(probe.saturation)))
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
