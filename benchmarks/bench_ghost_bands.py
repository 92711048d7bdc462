"""What a cheaper ghost statistic would lose: the χ² test on every k-th band (issue 16).

The default merge accumulates the χ² consistency statistic of every band of every pixel;
it is what keeps the merge at ~2× a read pass (radiance only: ~1.3×; the issue's target
is 1.6×). A statistic on every k-th band would cost about 1/k of it (session 30 measured
a bound for k = 4: ~1.65× a read pass). This script measures the other side of that
trade: which moving pixels the test still flags when its χ² and degrees of freedom come
from every k-th band only (the same noise model, the same detector, `mehs.synthesis.
ghost.detect_ghosts`), on the simulator's moving scenes with the moving patch at full,
1/10 and 1/30 of its brightness. The truth is the simulator's: pixels whose radiance
changes between the exposures, binned by the significance of that change over all the
bands, ``√Σ_b (Δ_b/σ_b)²`` for the pair of exposures where it is largest (σ_b the noise
of the difference: photon, dark-current and read noise of both exposures,
:mod:`mehs.capture.sensor`'s model; bands either exposure saturates left out). On every
k-th band a change spread over the spectrum keeps about 1/√k of it.

Two recalls per bin: of the test itself (each pixel's χ² against its threshold, no
clean-up) and of the final mask (the detector's defaults: groups under 3 pixels
dropped, the mask grown by one pixel, which also takes in a moving object's weak
fringe beside its flagged core).

The other cheaper statistic, **binned bands** (rows ``b2``, ``b4``, ``b8``): the χ² of the
sums of k adjacent bands (each exposure's dark-subtracted levels summed, its zero-signal
variance ×k), so a kernel would form k times fewer weights and sums. A change that keeps
its sign over k neighbouring bands (3 nm apart on a Specim IQ) keeps all its significance
there instead of 1/√k. It is computed here in numpy (``_chi2_binned``: an exposure is used
in a bin where none of the bin's bands saturates; the pooled Poisson estimate's weights, as
the merge's; no censored residuals, nor the merge's finer choice of samples), so its
all-band form is printed too (row ``b1``): the binned rows compare with that row, and
``b1`` with the merge's own statistic (row 1) shows what the simplifications change.

Run: ``python benchmarks/bench_ghost_bands.py`` (``--quick``: one seed, two scenes). No
timing: the machine's load is printed as by every benchmark, but changes nothing here.
Prints, per k and bin, those recalls; static pixels flagged by the final mask (false
alarms, more than two pixels from any moving one) and the overlap (IoU) of the final
mask with the all-band one.
"""

from __future__ import annotations

import argparse
import os
import sys

import numpy as np

sys.path.insert(0, os.path.join(os.path.dirname(__file__), ".."))
sys.path.insert(0, os.path.dirname(__file__))

from mehs.capture.scene import SPECIM_IQ_WAVELENGTHS, make_scene  # noqa: E402
from mehs.capture.sensor import SensorModel  # noqa: E402
from mehs.capture.simulate import simulate_bracket  # noqa: E402
from mehs.cube import SpectralCube  # noqa: E402
from mehs.synthesis.bracket import Bracket  # noqa: E402
from mehs.synthesis.fuse import estimate_noise  # noqa: E402
from mehs.synthesis.ghost import detect_ghosts  # noqa: E402
from mehs.synthesis.merge import merge_bracket  # noqa: E402
from mehs.synthesis.response import ResponseCurve  # noqa: E402

STEPS = (1, 2, 4, 8)
#: bin widths of the binned statistic (1: its all-band form, the binned rows' reference)
BINNED = (1, 2, 4, 8)
#: bins of the all-band significance of the change, in σ (the last is open)
BINS = (3.0, 10.0, 30.0, 100.0)


def _scene_bracket(kind, seed, contrast, size, times):
    sc = make_scene(kind, lines=size, samples=size, wavelengths=SPECIM_IQ_WAVELENGTHS,
                    seed=seed, motion=True)
    if sc._blob_spectrum is not None and contrast != 1.0:
        # the reference exposure's radiance holds the patch at its first place: dim it
        # there too (radiance_at(0) is the radiance itself)
        spec = sc._blob_spectrum
        sc.radiance = np.maximum(sc.radiance - np.float32(1.0 - contrast)
                                 * sc._blob(0)[..., None] * spec[None, None, :], 0.0)
        sc._blob_spectrum = spec * np.float32(contrast)
    sen = SensorModel(seed=seed)
    sim = simulate_bracket(sc, sen, list(times), seed=seed)
    b = Bracket([SpectralCube(e, sc.wavelengths) for e in sim.exposures], list(sim.darks),
                [None] * len(times), sim.times_ms, sc.wavelengths, bit_depth=12)
    return sc, sen, b


def _chi2_binned(b, sat, noise, k):
    """The χ² consistency statistic of sums of ``k`` adjacent bands, and its degrees of
    freedom, per pixel (float64 ``(lines, samples)``, int ``(lines, samples)``).

    Per bin and exposure ``j``: ``y_j`` the sum of the dark-subtracted levels, used where
    no band of the bin saturates; ``x_j = y_j/t_j`` with variance ``(g·x̂·t_j + k·a_j)/t_j²
    + r²·x̂²`` from the pooled estimate ``x̂ = max(Σy/Σt, 0)`` (gain ``g``, zero-signal
    variance ``a_j`` and relative noise ``r`` of the merge's noise model); the statistic is
    ``Σw(x − x̄)²`` about the inverse-variance mean with ``n − 1`` dof where ``n ≥ 2``
    exposures are used. Bands past the last whole bin are left out."""
    nl, ns, nb = b.exposures[0].data.shape
    m = nb // k
    t = np.asarray(b.times_ms, dtype=np.float64)
    avar = noise.zero_signal_variance(t)
    s = np.asarray(sat, dtype=np.float64)[: m * k].reshape(m, k)
    ys, oks = [], []
    for j, e in enumerate(b.exposures):
        raw = np.asarray(e.data, dtype=np.float64)[..., : m * k].reshape(nl, ns, m, k)
        d = 0.0 if b.darks[j] is None else np.asarray(b.darks[j], np.float64)
        if np.ndim(d) == 3:
            d = d.mean(axis=0)
        d = d[..., : m * k].reshape(ns, m, k) if np.ndim(d) else d
        ys.append((raw - d).sum(axis=3))
        oks.append((raw < s).all(axis=3))
    y = np.stack(ys)
    ok = np.stack(oks)
    tt = t[:, None, None, None]
    xp = np.maximum((ok * y).sum(0) / np.maximum((ok * tt).sum(0), 1e-300), 0.0)
    var = (noise.gain * xp * tt + k * avar[:, None, None, None]) / tt ** 2 \
        + noise.relative ** 2 * xp ** 2
    w = ok / var
    x = y / tt
    sw = w.sum(0)
    swx = (w * x).sum(0)
    q = np.where(sw > 0, (w * x * x).sum(0) - swx * swx / np.where(sw > 0, sw, 1.0), 0.0)
    n = ok.sum(0)
    two = n >= 2
    return np.where(two, np.maximum(q, 0.0), 0.0).sum(axis=2), np.where(two, n - 1, 0).sum(axis=2)


def _change_in_sigma(sc, sen, times, P):
    """Per pixel: the significance of the change of its radiance between two exposures
    over all its bands, ``√Σ_b (Δ_b/σ_b)²`` (σ_b: that difference's noise, both exposures'
    photon, dark-current and read noise in radiance units; a band either exposure
    saturates is left out), for the pair of exposures where it is largest — the
    square root of the all-band χ²'s non-centrality for that pair."""
    per_e = sen.qe_for(sc.radiance.shape[2], sc.wavelengths) * sen.radiance_to_e_per_ms
    full = min(sen.full_well_e,
               (0.98 * (2 ** sen.bit_depth - 1) - sen.black_level_dn) / sen.gain_dn_per_e)
    rad = [sc.radiance_at(k).astype(np.float64) for k in range(P)]
    var, ok = [], []
    for k, t in enumerate(times):
        e = rad[k] * per_e * t + sen.dark_current_e_per_ms * t
        var.append((e + sen.read_noise_e ** 2) / (per_e * t) ** 2)
        ok.append(e < full)
    best = np.zeros(rad[0].shape[:2])
    for j in range(P):
        for k in range(j + 1, P):
            z2 = (rad[k] - rad[j]) ** 2 / (var[j] + var[k])
            best = np.maximum(best, np.where(ok[j] & ok[k], z2, 0.0).sum(axis=2))
    return np.sqrt(best)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--size", type=int, default=96)
    args = ap.parse_args(argv)
    seeds = (1,) if args.quick else (1, 2)
    kinds = ("colorchecker", "window") if args.quick else ("colorchecker", "window", "lamp",
                                                            "ramp")
    times = (0.5, 2.0, 8.0)
    nbins = len(BINS) + 1
    names = [str(k) for k in STEPS] + [f"b{k}" for k in BINNED]
    rows = {n: {"test": np.zeros(nbins), "mask": np.zeros(nbins), "n": np.zeros(nbins),
                "fa": 0, "static": 0, "iou": []} for n in names}
    from scipy.ndimage import binary_dilation

    for kind in kinds:
        for seed in seeds:
            for contrast in (1.0, 0.1, 1 / 30):
                sc, sen, b = _scene_bracket(kind, seed, contrast, args.size, times)
                P = len(times)
                truth = sc.moved_between(range(P))
                which = np.digitize(_change_in_sigma(sc, sen, times, P)[truth], BINS)
                sat = np.full(b.shape[2], 0.98 * 4095, np.float32)
                noise, _ = estimate_noise(b, ResponseCurve.linear(12), sat)
                near = binary_dilation(truth, iterations=2)
                stats = {}
                for k in STEPS:
                    sel = slice(None, None, k)
                    mr = merge_bracket([e.data[..., sel] for e in b.exposures], b.times_ms,
                                       darks=[None if d is None else d[..., sel] for d in b.darks],
                                       bit_depth=12, saturation=sat[sel], noise=noise)
                    stats[str(k)] = (mr.chi2, mr.dof, "1")
                    if k == 1:
                        level = mr.mean_radiance
                for k in BINNED:
                    stats[f"b{k}"] = (*_chi2_binned(b, sat, noise, k), "b1")
                masks = {}
                for name in names:
                    chi2, dof, ref = stats[name]
                    kw = dict(scale="auto", level=level)
                    test = detect_ghosts(chi2, dof, min_pixels=1, grow=0, **kw).mask
                    mask = masks[name] = detect_ghosts(chi2, dof, **kw).mask
                    r = rows[name]
                    r["test"] += np.bincount(which, weights=test[truth], minlength=nbins)
                    r["mask"] += np.bincount(which, weights=mask[truth], minlength=nbins)
                    r["n"] += np.bincount(which, minlength=nbins)
                    r["fa"] += int((mask & ~near).sum())
                    r["static"] += int((~near).sum())
                    # b1 against the merge's own mask; the other rows against their family's
                    # all-band row
                    other = masks["1" if name == "b1" else ref]
                    union = (mask | other).sum()
                    r["iou"].append(1.0 if union == 0 else (mask & other).sum() / union)
    edges = ("<3σ",) + tuple(f"{lo:g}-{hi:g}σ" for lo, hi in zip(BINS[:-1], BINS[1:])) + (
        f"≥{BINS[-1]:g}σ",)
    print(f"ghost masks from the χ² of every k-th band (rows k) and of sums of k adjacent "
          f"bands (rows bk): {len(kinds)} scenes × {len(seeds)} seeds × 3 patch brightnesses, "
          f"{args.size}² × {len(SPECIM_IQ_WAVELENGTHS)} bands, times {times} ms")
    print("moving pixels flagged (the test alone / the final mask), by the all-band "
          "significance of their change:")
    print(f"{'k':>3} " + " ".join(f"{e:>13}" for e in edges) + f" {'false alarms':>13} "
          f"{'IoU vs all':>11}")
    n = rows["1"]["n"]
    print(f"{'n':>3} " + " ".join(f"{int(x):>13d}" for x in n))
    for name in names:
        r = rows[name]
        cells = []
        for t, m, c in zip(r["test"], r["mask"], r["n"]):
            cells.append(f"{t / c:.3f} / {m / c:.3f}" if c else "—")
        print(f"{name:>3} " + " ".join(f"{c:>13}" for c in cells)
              + f" {r['fa'] / max(r['static'], 1):>13.2e} {np.mean(r['iou']):>11.3f}")
    print("IoU vs all: rows k against row 1 (the merge's statistic); rows bk against b1 (the "
          "binned statistic's all-band form), b1 against row 1")
    return 0


if __name__ == "__main__":
    from _load import run_reporting_load

    run_reporting_load(main)
