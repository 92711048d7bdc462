"""SSR conversion timings on a 2048×1024 image (paper Table 5), with ratios.

Reference measured in the same run: colour-science's per-pixel
``RGB_to_sd_Smits1999`` (and ``RGB_to_sd_Mallett2019``) timed on a random
sample of pixels and extrapolated to the whole image. The paper's Smits time
(0.788 s, CPU i9-11900) is printed for orientation. Target: vectorised Smits
≤ 0.3 s.

Usage: python benchmarks/bench_ssr.py [--quick]
"""

from __future__ import annotations

import argparse
import time

import numpy as np


def best_of(fn, repeat):
    best = np.inf
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t0)
    return best


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--quick", action="store_true", help="fewer repeats and a smaller sample")
    args = ap.parse_args(argv)
    repeat = 2 if args.quick else 5
    sample = 300 if args.quick else 3000

    import colour

    from mehs.rgb import WAVELENGTHS_31 as W
    from mehs.ssr.baselines import (Mallett2019, RegressionModel, Smits1999,
                                    RGB_to_spectra_Smits1999)
    from mehs.ssr.luminance import restore_luminance
    from mehs.ssr.pipeline import predict

    h, w = 1024, 2048
    n = h * w
    rng = np.random.default_rng(0)
    rgb = (rng.gamma(1.0, 1.0, (h, w, 3)) * 4).astype(np.float32)

    smits, mallett = Smits1999(), Mallett2019()
    xs = rng.uniform(0, 1, (4000, 3))
    spectra = RGB_to_spectra_Smits1999(xs) * rng.uniform(0.5, 1.5, (4000, 31))
    reg = RegressionModel.fit(xs, spectra, degree=2)
    for m in (smits, mallett, reg):
        m(rgb[:8, :8])

    pix = rgb.reshape(-1, 3)[rng.choice(n, sample, replace=False)].astype(np.float64)
    colour.recovery.RGB_to_sd_Smits1999(pix[0])[W]
    t_cs = best_of(lambda: [colour.recovery.RGB_to_sd_Smits1999(p)[W] for p in pix], 1)
    t_cs_full = t_cs / sample * n
    t_cm = best_of(lambda: [colour.recovery.RGB_to_sd_Mallett2019(p)[W] for p in pix], 1)
    t_cm_full = t_cm / sample * n

    rows = []
    t = best_of(lambda: smits(rgb), repeat)
    rows.append(("Smits 1999 (mehs, vectorised)", t, t_cs_full))
    rows.append((f"Smits 1999 (colour per pixel, {sample} px extrapolated)", t_cs_full, t_cs_full))
    t = best_of(lambda: mallett(rgb), repeat)
    rows.append(("Mallett 2019 (mehs, one matrix product)", t, t_cm_full))
    rows.append((f"Mallett 2019 (colour per pixel, {sample} px extrapolated)", t_cm_full, t_cm_full))
    t = best_of(lambda: reg(rgb), repeat)
    rows.append(("root-polynomial regression, degree 2", t, t_cs_full))
    S = smits(rgb)
    t = best_of(lambda: restore_luminance(S, rgb, W), repeat)
    rows.append(("luminance restoration alone", t, t_cs_full))
    t = best_of(lambda: predict(smits, rgb, preprocess=True, restore=True), repeat)
    rows.append(("Smits + Reinhard + restoration (pipeline)", t, t_cs_full))

    print(f"SSR conversion of one {w}×{h} image (float32 RGB → 31 bands), best of {repeat}")
    print(f"{'method':58s} {'seconds':>9s} {'speed-up vs colour per pixel':>29s} "
          f"{'÷ paper Smits 0.788 s':>22s}")
    for name, sec, ref in rows:
        print(f"{name:58s} {sec:9.3f} {ref / sec:28.1f}× {sec / 0.788:21.2f}×")
    t_smits = rows[0][1]
    print(f"\ntarget: vectorised Smits ≤ 0.3 s → {t_smits:.3f} s "
          f"{'PASS' if t_smits <= 0.3 else 'FAIL'}")
    return 0


if __name__ == "__main__":
    from _load import run_reporting_load  # the load this run saw (issue 16)

    run_reporting_load(main)
