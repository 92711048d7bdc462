"""Slowdown of the BLAS-heavy hot paths when one other CPU-bound process competes for the cores.

    python benchmarks/bench_load.py [--quick] [--repeat N]

For each path the median of ``--repeat`` calls is timed twice in this run:
without and with one competing busy process (a Python loop spinning on one
core, started here and stopped after the timing). The printed ratio
``loaded / unloaded`` is what the target of issue 16 is about (≤ 1.5×); it does
not depend on how fast the machine is. Each path runs as mehs runs it (numpy's
BLAS pinned to one thread, :mod:`mehs._blas`) and, as the reference, with the
BLAS left at its default thread count (the behaviour before issue 16), so both
ratios come from the same run under the same background load, which is printed
beside every phase (1-minute load average and the CPU share used by others).

Paths: Smits 1999 and Mallett 2019 on a 512×512 RGB image, and the
"resample from a memory map" stage (a 512×512×204 uint16 BIL file → 31 bands).
"""

from __future__ import annotations

import argparse
import contextlib
import multiprocessing as mp
import os
import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from _load import load_line  # noqa: E402


def _spin(stop) -> None:
    x = 0
    while not stop.is_set():
        for _ in range(100_000):
            x += 1


@contextlib.contextmanager
def competing_process(n: int = 1):
    """``n`` CPU-bound processes running for the duration of the block."""
    stop = mp.Event()
    procs = [mp.Process(target=_spin, args=(stop,), daemon=True) for _ in range(n)]
    for p in procs:
        p.start()
    time.sleep(0.5)  # let the scheduler see them as busy
    try:
        yield
    finally:
        stop.set()
        for p in procs:
            p.join(5)


def median_time(fn, repeat: int) -> float:
    fn()
    ts = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        ts.append(time.perf_counter() - t0)
    return statistics.median(ts)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--quick", action="store_true", help="256² images and 5 repeats")
    ap.add_argument("--repeat", type=int, default=None)
    args = ap.parse_args(argv)
    n = 256 if args.quick else 512
    repeat = args.repeat or (5 if args.quick else 9)

    import mehs.ssr.baselines as baselines
    import mehs.synthesis.resample as resample
    from mehs.cube import SpectralCube
    from mehs.rgb import WAVELENGTHS_31

    rng = np.random.default_rng(0)
    rgb = rng.gamma(1.0, 1.0, (n, n, 3)).astype(np.float32)
    nb = 204
    wl = np.linspace(397.32, 1003.58, nb)
    tmp = Path(tempfile.mkdtemp(prefix="mehs_bench_load_"))
    path = tmp / "cube.bil"
    mm = np.memmap(path, dtype=np.uint16, mode="w+", shape=(n, nb, n))
    mm[:] = rng.integers(0, 4096, (n, nb, n), dtype=np.uint16)
    mm.flush()
    del mm
    view = np.memmap(path, dtype=np.uint16, mode="r", shape=(n, nb, n)).transpose(0, 2, 1)
    cube = SpectralCube(view, wl)

    def read_pass():  # no BLAS: what the scheduler alone does to a 1-thread pass
        acc = 0
        for l0 in range(0, n, 32):
            acc += int(np.asarray(view[l0:l0 + 32]).astype(np.float32).sum(dtype=np.float64))
        return acc

    paths = [
        ("floor: read + convert the memmap (no BLAS)", resample, read_pass),
        (f"Smits 1999, {n}×{n}", baselines,
         lambda: baselines.RGB_to_spectra_Smits1999(rgb)),
        (f"Mallett 2019, {n}×{n}", baselines,
         lambda: baselines.RGB_to_spectra_Mallett2019(rgb)),
        (f"resample memmap {n}×{n}×{nb} uint16 BIL → 31", resample,
         lambda: resample.resample_cube(cube, WAVELENGTHS_31)),
    ]
    pinned = {m: m.single_thread_blas for _, m, _ in paths}

    def run(module, fn, mode):
        module.single_thread_blas = pinned[module] if mode == "1 thread" else contextlib.nullcontext
        try:
            return median_time(fn, repeat)
        finally:
            module.single_thread_blas = pinned[module]

    from threadpoolctl import threadpool_info

    blas = [f"{i['internal_api']} {i['num_threads']} threads" for i in threadpool_info()
            if i["user_api"] == "blas"]
    print(f"{os.cpu_count()} CPUs; numpy BLAS default: {', '.join(blas) or 'unknown'}; "
          f"median of {repeat}")
    modes = ("1 thread", "BLAS default")

    def modes_of(label):
        return modes[:1] if label.startswith("floor") else modes
    res: dict[tuple[str, str, bool], float] = {}
    print("unloaded phase: ", load_line())
    for label, module, fn in paths:
        for mode in modes_of(label):
            res[label, mode, False] = run(module, fn, mode)
    with competing_process(1):
        print("loaded phase:   ", load_line(), "(+1 busy process of this benchmark)")
        for label, module, fn in paths:
            for mode in modes_of(label):
                res[label, mode, True] = run(module, fn, mode)
    print(f"{'path':<46} {'BLAS':<13} {'unloaded s':>10} {'loaded s':>9} {'slowdown':>9}")
    for label, _, _ in paths:
        for mode in modes_of(label):
            a, b = res[label, mode, False], res[label, mode, True]
            tag = ("scheduler floor" if label.startswith("floor") else
                   "mehs" if mode == "1 thread" else "reference (before issue 16)")
            print(f"{label:<46} {mode:<13} {a:10.4f} {b:9.4f} {b / a:8.2f}×  {tag}")
    print("target (issue 16): mehs slowdown with one competing busy process ≤ 1.5×; "
          "the floor row is\n"
          "what the same competition does to a single-threaded pass that uses no BLAS at all")
    del view, cube
    os.unlink(path)
    os.rmdir(tmp)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
