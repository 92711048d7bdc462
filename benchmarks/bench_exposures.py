"""Merge time per exposure for brackets of 3 to 16 exposures (issue 16, session 36).

The one-pass merge kernels keep each sample's state in registers by unrolling their
exposure loop; beyond 3 exposures LLVM's default tuning left it rolled and the kernels
ran scalar (7–11× the time per exposure), unseen because the other benchmarks merge 3.
Here every method merges the same scene (lines × 512 × 204 bands, uint16, in memory)
bracketed by 3, 5, 8 and 16 exposures a factor of 2 apart, with the ghost statistic
``auto`` gives (bins of 4 bands) and per band. The reference is the 3-exposure bracket of
the same method and statistic, in the same run: the ratio is the time per exposure
against it (target ≤ 1.3×: a longer bracket costs what its extra reads cost).

    python benchmarks/bench_exposures.py [--lines 64] [--repeat 5]

The first run compiles (and stores) a kernel per method, statistic and exposure count
(seconds each, a child process beyond 3 exposures); later runs load them.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from _load import load_line  # noqa: E402

from mehs.synthesis.merge import NoiseModel, merge_bracket  # noqa: E402

EXPOSURES = (3, 5, 8, 16)
METHODS = ("poisson", "debevec", "robertson", "inverse-variance")


def bracket(lines: int, P: int, rng: np.random.Generator):
    """A BIL stack (lines, samples, bands views) of ``P`` exposures over the same scene
    (radiance 1–300 spanning the bracket), with its times and darks."""
    ns, nb = 512, 204
    scene = np.random.default_rng(0)
    E = (scene.uniform(1, 300, (lines, ns, 1)) * scene.uniform(0.3, 1, (1, 1, nb))
         ).astype(np.float32)
    t = [2.0 ** (j - (P - 3)) for j in range(P)]      # the longest 4: as the 3-bracket's
    stack = []
    for tj in t:
        y = E * np.float32(tj) + 60 + rng.normal(0, 3, E.shape).astype(np.float32)
        raw = np.clip(np.rint(y), 0, 4095).astype(np.uint16)
        stack.append(np.ascontiguousarray(raw.transpose(0, 2, 1)).transpose(0, 2, 1))
    return stack, t, [np.full((ns, nb), 60.0, np.float32)] * P


def median_time(fn, repeat: int):
    """Median wall time of ``repeat`` calls after a warm one, and the last result."""
    out = fn()                                # compile or load, warm
    ts = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        out = fn()
        ts.append(time.perf_counter() - t0)
    return statistics.median(ts), out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--lines", type=int, default=64)
    ap.add_argument("--repeat", type=int, default=5)
    args = ap.parse_args()
    print(load_line())
    rng = np.random.default_rng(1)
    noise = NoiseModel(1.5, 3.0)
    per_exp: dict[tuple, float] = {}
    print(f"{'method':18s} {'statistic':10s} {'exposures':>9s} {'seconds':>9s} "
          f"{'ms/exposure':>12s}  ratio to 3 exposures")
    for P in EXPOSURES:
        stack, t, darks = bracket(args.lines, P, rng)
        for method in METHODS:
            for bins in ("auto", 1):
                took, res = median_time(
                    lambda: merge_bracket(stack, t, method=method, darks=darks, noise=noise,
                                          consistency_bins=bins), args.repeat)
                got = res.info["consistency_bins"]
                what = f"bins {got}" if bins == "auto" else "per band"
                per_exp[method, bins, P] = took / P
                ref = per_exp[method, bins, EXPOSURES[0]]
                print(f"{method:18s} {what:10s} {P:9d} {took:9.3f} {1000 * took / P:12.2f}  "
                      f"{per_exp[method, bins, P] / ref:.2f}× "
                      f"{'(reference)' if P == EXPOSURES[0] else '(target ≤ 1.3×)'}",
                      flush=True)
    print(load_line())


if __name__ == "__main__":
    main()
