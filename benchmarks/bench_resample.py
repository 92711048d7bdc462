"""Resampling benchmark: one 512×512×204 float32 cube → 31 bands (400:700:10), target ≤ 0.2 s.

Usage: python benchmarks/bench_resample.py [--quick] [--size L S B]

Variants (same Gaussian matrix, same cube, one run):
- "mehs resample_cube (in memory)": the library call, ``cube @ M.T`` in float32,
  chunked over lines, only the source bands some target sees;
- "mehs resample_cube (ENVI memmap, bil)": the same from a float32 ENVI file
  opened memory-mapped (page cache warm), as `mehs resample` runs;
- references: "per-pixel matrix" — ``M @ spectrum`` for each pixel in a Python
  loop (timed on a sample of pixels and extrapolated to the whole cube), and
  "SPy BandResampler naive" — ``spectral.BandResampler(...)(spectrum)`` per
  pixel (sampled and extrapolated), plus building SPy's matrix vs ours.
Extras for the pipeline budget: hdr_rgb on the 31-band result, ldr_rgb and the
Reinhard preview.

Times are medians of repeated runs; ratios are "reference time / this time"
(how many times faster than the per-pixel reference).
"""

from __future__ import annotations

import argparse
import tempfile
from pathlib import Path

import numpy as np

from _timing import median_time


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="fewer repeats and sampled pixels")
    ap.add_argument("--size", type=int, nargs=3, default=(512, 512, 204),
                    metavar=("LINES", "SAMPLES", "BANDS"))
    args = ap.parse_args(argv)
    reps = 3 if args.quick else 7
    n_sample = 2000 if args.quick else 10000

    import spectral

    from mehs.cube import SpectralCube
    from mehs.io.envi import read_envi, write_envi
    from mehs.preview import tonemap
    from mehs.rgb import WAVELENGTHS_31, hdr_rgb, ldr_rgb
    from mehs.synthesis.resample import resample_cube, resampling_matrix

    L, S, B = args.size
    rng = np.random.default_rng(0)
    wl = np.linspace(397.32, 1003.58, B)
    data = (rng.random((L, S, B), dtype=np.float32) * 100).astype(np.float32)
    cube = SpectralCube(data, wl, units="relative radiance")
    n_pix = L * S
    rows: list[tuple[str, float]] = []

    t_build = median_time(lambda: resampling_matrix(wl, WAVELENGTHS_31), reps)
    t_build_spy = median_time(
        lambda: spectral.BandResampler(list(wl), list(WAVELENGTHS_31), None, [10.0] * 31), reps)
    m = resampling_matrix(wl, WAVELENGTHS_31)

    resample_cube(cube)  # warm-up (BLAS threads, scipy import)
    t_mem = median_time(lambda: resample_cube(cube), reps)
    rows.append(("mehs resample_cube (in memory)", t_mem))

    with tempfile.TemporaryDirectory() as tmp:
        hdr = write_envi(Path(tmp) / "cube.hdr", cube, dtype="float32", interleave="bil",
                         data_ext=".dat")
        mm = read_envi(hdr, memmap=True)
        resample_cube(mm)
        t_mm = median_time(lambda: resample_cube(read_envi(hdr, memmap=True)), reps)
        rows.append(("mehs resample_cube (ENVI memmap, bil)", t_mm))
        del mm

    flat = data.reshape(-1, B)
    idx = rng.choice(n_pix, size=min(n_sample, n_pix), replace=False)

    def per_pixel():
        for i in idx:
            m @ flat[i]

    t_pp = median_time(per_pixel, max(1, reps // 2)) * n_pix / idx.size
    rows.append((f"per-pixel matrix (extrapolated from {idx.size} px)", t_pp))

    spy = spectral.BandResampler(list(wl), list(WAVELENGTHS_31), None, [10.0] * 31)

    def spy_naive():
        for i in idx:
            spy(flat[i])

    t_spy = median_time(spy_naive, max(1, reps // 2)) * n_pix / idx.size
    rows.append((f"SPy BandResampler naive (extrapolated from {idx.size} px)", t_spy))

    hs = resample_cube(cube).data
    t_rgb = median_time(lambda: hdr_rgb(hs, WAVELENGTHS_31), reps)
    rgb = hdr_rgb(hs, WAVELENGTHS_31)
    t_ldr = median_time(lambda: ldr_rgb(rgb), reps)
    t_tm = median_time(lambda: tonemap(rgb), reps)

    print(f"cube {L}×{S}×{B} float32 ({data.nbytes / 1e6:.0f} MB) → 31 bands, Gaussian 10 nm; "
          f"median of {reps}")
    print(f"{'variant':58s} {'time [s]':>10s} {'× faster than per-pixel':>24s} "
          f"{'× faster than SPy naive':>24s}")
    for name, t in rows:
        print(f"{name:58s} {t:10.4f} {t_pp / t:24.1f} {t_spy / t:24.1f}")
    print()
    print(f"{'matrix build: mehs resampling_matrix':58s} {t_build:10.5f}   "
          f"(SPy create_resampling_matrix {t_build_spy:.5f} s, ratio {t_build_spy / t_build:.1f}×)")
    print(f"{'hdr_rgb on the 31-band result':58s} {t_rgb:10.4f}")
    print(f"{'ldr_rgb (average metering, sRGB encode)':58s} {t_ldr:10.4f}")
    print(f"{'tonemap Reinhard2002 preview':58s} {t_tm:10.4f}")
    target = 0.2 * (L * S * B) / (512 * 512 * 204)
    verdict = "PASS" if t_mem <= target else "FAIL"
    print(f"\ntarget: in-memory resample ≤ {target:.3f} s → {verdict} ({t_mem:.4f} s)")
    return 0


if __name__ == "__main__":
    from _load import run_reporting_load  # the load this run saw (issue 16)

    run_reporting_load(main)
