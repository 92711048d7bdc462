"""Benchmark: a full simulated bracket captured through the drivers over loopback TCP.

    python benchmarks/bench_capture.py [--quick] [--size N] [--auto]

The simulated stage + camera run in a separate process (`mehs sim-device`), the
drivers and the capture session in this one — as with real hardware. The
reference measured in the same run is `simulate_bracket` (the same exposures
computed without any transport); the table gives each stage's time and its
ratio to that reference. Target (issue 3): a 512×512×204 bracket in < 60 s.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from _simdevice import start_sim  # noqa: E402

TIMES = [0.05, 0.8, 12.8]




def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true", help="128×128 instead of 512×512")
    ap.add_argument("--size", type=int, default=None)
    ap.add_argument("--auto", action="store_true", help="include auto-exposure in the capture")
    args = ap.parse_args()
    size = args.size or (128 if args.quick else 512)

    from mehs.capture.camera import LineCamera
    from mehs.capture.scene import make_scene
    from mehs.capture.sensor import SensorModel
    from mehs.capture.session import capture_scene
    from mehs.capture.simulate import simulate_bracket
    from mehs.capture.zaber import ZaberStage

    rows = []
    t0 = time.perf_counter()
    scene = make_scene(lines=size, samples=size)
    rows.append(("make_scene", time.perf_counter() - t0))
    t0 = time.perf_counter()
    ref = simulate_bracket(scene, SensorModel(), TIMES)
    t_ref = time.perf_counter() - t0
    rows.append(("simulate_bracket (reference, no transport)", t_ref))
    del ref

    t0 = time.perf_counter()
    proc, urls = start_sim(size)
    rows.append(("start sim-device process", time.perf_counter() - t0))
    marks = []
    try:
        with tempfile.TemporaryDirectory() as tmp:
            stage = ZaberStage.open(urls["stage"], timeout=5.0)
            camera = LineCamera.open(urls["camera"], timeout=5.0)
            t0 = time.perf_counter()
            marks.append(("start", t0))
            capture_scene(stage, camera, Path(tmp) / "scene", times_ms=None if args.auto else TIMES,
                          auto=args.auto, lines=size, progress=False,
                          log=lambda m: marks.append((m, time.perf_counter())))
            t_cap = time.perf_counter() - t0
            stage.close()
            camera.close()
    finally:
        proc.terminate()
        proc.wait()
    prev = marks[0][1]
    for msg, t in marks[1:]:
        rows.append((f"  {msg[:60]}", t - prev))
        prev = t
    rows.append((f"capture through drivers, {size}×{size}×204 × {len(TIMES)} (total)", t_cap))

    n_lines = len(TIMES) * (size + 32)
    times_txt = "auto-exposure (reference at " + str(TIMES) + " ms)" if args.auto else f"times {TIMES} ms"
    print(f"\nbench_capture: {size}×{size}×204, {times_txt}, {n_lines} line transfers "
          f"({n_lines * size * 204 * 2 / 1e6:.0f} MB)")
    print(f"{'stage':<66} {'seconds':>9} {'× simulate_bracket':>19}")
    for name, sec in rows:
        print(f"{name:<66} {sec:>9.2f} {sec / t_ref:>19.2f}")
    print(f"\nper line through drivers: {t_cap / n_lines * 1e3:.2f} ms; "
          f"target < 60 s for 512×512: {'met' if t_cap < 60 or size != 512 else 'NOT met'}")
    return 0


if __name__ == "__main__":
    from _load import run_reporting_load  # the load this run saw (issue 16)

    run_reporting_load(main)
