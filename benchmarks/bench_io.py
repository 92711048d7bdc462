"""I/O benchmark: `mehs info` / read_envi open+sample vs one full read pass; write throughput.

Usage: python benchmarks/bench_io.py [--quick] [--size L S B]

All on a Specim-IQ-sized cube (512 lines × 512 samples × 204 bands, uint16,
bil, 107 MB) written to a temporary folder. Times are medians of repeated
runs; the file is in the page cache for every variant (read from cache, not
disk), so the ratios compare work done, not disk speed.

References measured in the same run:
- "full read pass": ``np.fromfile`` of the whole data file (what reading the
  cube costs at minimum) — `mehs info` must be a small fraction of it;
- "numpy tofile": writing the same bytes with no transpose or checks;
- "SPy save_image": spectral.envi.save_image of the same cube, bil.
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from _timing import median_time


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="fewer repeats")
    ap.add_argument("--size", type=int, nargs=3, default=(512, 512, 204),
                    metavar=("LINES", "SAMPLES", "BANDS"))
    args = ap.parse_args(argv)
    reps = 3 if args.quick else 7

    import spectral.io.envi as spy_envi

    from mehs.cli.info import describe
    from mehs.cube import SpectralCube
    from mehs.io.envi import read_envi, write_envi

    L, S, B = args.size
    rng = np.random.default_rng(0)
    data = rng.integers(0, 4096, (L, S, B), dtype=np.uint16)
    cube = SpectralCube(data, np.linspace(397.32, 1003.58, B), integration_time_ms=10.0,
                        default_bands=(min(69, B - 1), min(52, B - 1), min(18, B - 1))
                        if B >= 3 else None)
    mb = data.nbytes / 1e6
    rows: list[tuple[str, float, str, str]] = []
    with tempfile.TemporaryDirectory(prefix="bench_io_") as td:
        d = Path(td)
        hp = d / "cube.hdr"
        t_write = median_time(lambda: write_envi(hp, cube, interleave="bil"), reps)
        t_tofile = median_time(lambda: data.tofile(d / "plain.bin"), reps)
        t_spy = median_time(lambda: spy_envi.save_image(str(d / "spy.hdr"), data,
                                                         interleave="bil", ext=".raw",
                                                         force=True), reps)
        raw = d / "cube.raw"
        t_full = median_time(lambda: np.fromfile(raw, dtype="<u2").sum(), reps)
        t_full_read = median_time(lambda: np.asarray(read_envi(hp, memmap=False).data), reps)
        t_open = median_time(lambda: read_envi(hp), reps * 3)
        t_info = median_time(lambda: describe(hp), reps * 3)
        t0 = time.perf_counter()
        res = subprocess.run([sys.executable, "-m", "mehs", "info", str(hp)],
                             capture_output=True, text=True)
        t_cli = time.perf_counter() - t0
        t1 = time.perf_counter()
        subprocess.run([sys.executable, "-c", "import mehs.cli"], capture_output=True)
        t_import = time.perf_counter() - t1
        if res.returncode != 0:
            print(res.stderr, file=sys.stderr)
            return 1

    ref_read = t_full
    rows += [
        ("full read pass (np.fromfile + sum)  [reference]", t_full, "1.00×", ""),
        ("read_envi(memmap=False) → (L,S,B) array", t_full_read, f"{t_full_read / ref_read:.2f}×",
         f"{mb / t_full_read:.0f} MB/s"),
        ("read_envi (memmap: header checks + map)", t_open, f"{t_open / ref_read:.4f}×", ""),
        ("mehs info core (describe, 64 sampled lines)", t_info, f"{t_info / ref_read:.4f}×", ""),
        ("mehs info CLI subprocess (incl. Python start)", t_cli, f"{t_cli / ref_read:.2f}×",
         f"python -c 'import mehs.cli' alone: {t_import:.3f} s"),
        ("numpy tofile, same bytes  [write reference]", t_tofile, "1.00×", f"{mb / t_tofile:.0f} MB/s"),
        ("write_envi bil (atomic, chunked, fsync)", t_write, f"{t_write / t_tofile:.2f}×",
         f"{mb / t_write:.0f} MB/s"),
        ("SPy envi.save_image bil", t_spy, f"{t_spy / t_tofile:.2f}×", f"{mb / t_spy:.0f} MB/s"),
    ]
    print(f"cube {L}×{S}×{B} uint16 bil, {mb:.1f} MB; median of {reps} runs "
          f"({reps * 3} for the fast rows); page-cached")
    w = max(len(r[0]) for r in rows)
    print(f"{'what':<{w}}  {'time (s)':>10}  {'ratio':>9}  note")
    for name, t, ratio, note in rows:
        print(f"{name:<{w}}  {t:>10.4f}  {ratio:>9}  {note}")
    print("read ratios are against the full read pass; write ratios against numpy tofile")
    return 0


if __name__ == "__main__":
    from _load import run_reporting_load  # the load this run saw (issue 16)

    run_reporting_load(main)
