"""What a cheaper ghost statistic would lose: the χ² test on every k-th band (issue 16).

The default merge accumulates the χ² consistency statistic of every band of every pixel;
it is what keeps the merge at ~2× a read pass (radiance only: ~1.3×; the issue's target
is 1.6×). A statistic on every k-th band would cost about 1/k of it (session 30 measured
a bound for k = 4: ~1.65× a read pass). This script measures the other side of that
trade: which moving pixels the test still flags when its χ² and degrees of freedom come
from every k-th band only (the same noise model, the same detector, `mehs.synthesis.
ghost.detect_ghosts`), on the simulator's moving scenes with the moving patch at full,
1/10 and 1/30 of its contrast. The truth is the simulator's: pixels whose radiance
changes between the exposures, binned by how much (the largest change over the bands,
in units of the photon and read noise of the longest unsaturated exposure at that
pixel's brightest band).

Run: ``python benchmarks/bench_ghost_bands.py`` (``--quick``: one seed, two scenes). No
timing: the machine's load is printed as by every benchmark, but changes nothing here.
Prints, per k: the fraction of truly moving pixels flagged in each bin of that change,
static pixels flagged (false alarms, beyond one pixel of the truth: the detector grows its
mask by one) and the overlap (IoU) of the mask with the all-band mask.
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
#: change bins in noise σ of the pixel's brightest band (the last is open)
BINS = (3.0, 10.0, 30.0, 100.0)


def _scene_bracket(kind, seed, contrast, size, times):
    sc = make_scene(kind, lines=size, samples=size, wavelengths=SPECIM_IQ_WAVELENGTHS,
                    seed=seed, motion=True)
    if sc._blob_spectrum is not None:
        sc._blob_spectrum = sc._blob_spectrum * np.float32(contrast)
        # the reference exposure's radiance holds its own share of the patch
        sc.radiance = sc.radiance_at(0)
    sen = SensorModel(seed=seed)
    sim = simulate_bracket(sc, sen, list(times), seed=seed)
    b = Bracket([SpectralCube(e, sc.wavelengths) for e in sim.exposures], list(sim.darks),
                [None] * len(times), sim.times_ms, sc.wavelengths, bit_depth=12)
    return sc, sen, b


def _change_in_sigma(sc, sen, times, P):
    """Per pixel: the largest change of the radiance between exposures over its bands,
    each in that band's noise σ of one exposure (photon, dark-current and read noise of
    the longest exposure that leaves it unsaturated, :mod:`mehs.capture.sensor`'s model)."""
    base = sc.radiance_at(0).astype(np.float64)
    delta = np.zeros(base.shape)
    top = base.copy()
    for k in range(1, P):
        rk = sc.radiance_at(k).astype(np.float64)
        delta = np.maximum(delta, np.abs(rk - base))
        top = np.maximum(top, rk)
    per_e = sen.qe_for(base.shape[2], sc.wavelengths) * sen.radiance_to_e_per_ms   # e-/ms
    full = min(sen.full_well_e,
               (0.98 * (2 ** sen.bit_depth - 1) - sen.black_level_dn) / sen.gain_dn_per_e)
    sigma = np.full(base.shape, np.inf)
    for t in times:
        e = top * per_e * t + sen.dark_current_e_per_ms * t
        s = np.sqrt(e + sen.read_noise_e ** 2) / (per_e * t)
        sigma = np.where(e < full, np.minimum(sigma, s), sigma)
    return (delta / sigma).max(axis=2)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--size", type=int, default=96)
    args = ap.parse_args(argv)
    seeds = (1,) if args.quick else (1, 2)
    kinds = ("colorchecker", "window") if args.quick else ("colorchecker", "window", "lamp",
                                                            "ramp")
    times = (0.5, 2.0, 8.0)
    rows = {k: {"hit": np.zeros(len(BINS) + 1), "n": np.zeros(len(BINS) + 1), "fa": 0,
                "static": 0, "iou": []} for k in STEPS}
    from scipy.ndimage import binary_dilation

    for kind in kinds:
        for seed in seeds:
            for contrast in (1.0, 0.1, 1 / 30):
                sc, sen, b = _scene_bracket(kind, seed, contrast, args.size, times)
                P = len(times)
                truth = sc.moved_between(range(P))
                change = _change_in_sigma(sc, sen, times, P)
                sat = np.full(b.shape[2], 0.98 * 4095, np.float32)
                noise, _ = estimate_noise(b, ResponseCurve.linear(12), sat)
                near = binary_dilation(truth, iterations=2)
                masks = {}
                for k in STEPS:
                    sel = slice(None, None, k)
                    mr = merge_bracket([e.data[..., sel] for e in b.exposures], b.times_ms,
                                       darks=[None if d is None else d[..., sel] for d in b.darks],
                                       bit_depth=12, saturation=sat[sel], noise=noise)
                    g = detect_ghosts(mr.chi2, mr.dof, scale="auto", level=mr.mean_radiance)
                    masks[k] = g.mask
                    r = rows[k]
                    which = np.digitize(change[truth], BINS)
                    r["hit"] += np.bincount(which, weights=g.mask[truth], minlength=len(BINS) + 1)
                    r["n"] += np.bincount(which, minlength=len(BINS) + 1)
                    r["fa"] += int((g.mask & ~near).sum())
                    r["static"] += int((~near).sum())
                    inter = (g.mask & masks[1]).sum()
                    union = (g.mask | masks[1]).sum()
                    r["iou"].append(1.0 if union == 0 else inter / union)
    edges = ("<3σ",) + tuple(f"{lo:g}-{hi:g}σ" for lo, hi in zip(BINS[:-1], BINS[1:])) + (
        f"≥{BINS[-1]:g}σ",)
    print(f"ghost masks from the χ² of every k-th band: {len(kinds)} scenes × {len(seeds)} "
          f"seeds × 3 contrasts, {args.size}² × {len(SPECIM_IQ_WAVELENGTHS)} bands, times "
          f"{times} ms")
    print("moving pixels flagged, by their largest change (noise σ of one exposure):")
    print(f"{'k':>3} " + " ".join(f"{e:>12}" for e in edges) + f" {'false alarms':>13} "
          f"{'IoU vs k=1':>11}")
    n = rows[1]["n"]
    print(f"{'n':>3} " + " ".join(f"{int(x):>12d}" for x in n))
    for k in STEPS:
        r = rows[k]
        frac = np.where(r["n"] > 0, r["hit"] / np.maximum(r["n"], 1), np.nan)
        print(f"{k:>3} " + " ".join(f"{f:>12.3f}" for f in frac)
              + f" {r['fa'] / max(r['static'], 1):>13.2e} {np.mean(r['iou']):>11.3f}")
    return 0


if __name__ == "__main__":
    from _load import run_reporting_load

    run_reporting_load(main)
