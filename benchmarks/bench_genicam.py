"""Benchmark: scan lines per second, GigE Vision (Aravis, loopback) vs the serial camera path.

    python benchmarks/bench_genicam.py [--quick] [--size N] [--time-ms T] [--oversample M]

The simulators run in separate processes — ``mehs sim-device --genicam`` (the
HS camera on Aravis's fake GigE Vision camera, 127.0.0.1) and ``mehs
sim-device`` (the serial line camera on TCP) — and the drivers here, as with
real hardware. For each path it scans ``size`` lines at one integration time,
stop-and-go (``step``) and at constant velocity (``continuous``), and prints
lines/s with the ratio to the **serial continuous** scan measured in the same
run (the reference). Continuous GigE Vision is limited by the simulated
camera's frame rate (100 Hz: every frame is computed in Python) divided by the
frames per line; a real camera free-runs at hundreds of Hz.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from _simdevice import start_sim  # noqa: E402




def measure(urls: dict, size: int, t_ms: float, oversample: float) -> list[tuple[str, float, dict]]:
    from mehs.cli.capture import open_camera
    from mehs.capture.scan import scan_continuous
    from mehs.capture.session import Scanner
    from mehs.capture.zaber import ZaberStage

    class _Args:
        timeout, wavelengths, dark_prompt = 2.0, None, False

    out = []
    with ZaberStage.open(urls["stage"]) as stage:
        if "WR" in stage.warnings():
            stage.home()
        cam = open_camera(urls["camera"], _Args())
        try:
            samples, bands = cam.shape()
            cam.set_integration_time(t_ms)
            sc = Scanner(stage, cam)
            sc.read(0)                                       # first-frame latency outside the timing
            t0 = time.perf_counter()
            for i in range(size):
                sc.read(i)
            out.append(("step", time.perf_counter() - t0, {}))
            t0 = time.perf_counter()
            _raw, info = scan_continuous(stage, cam, lines=size, samples=samples, bands=bands, pitch=64,
                                         start_position=0, t_ms=t_ms, oversample=oversample)
            out.append(("continuous", time.perf_counter() - t0, info))
        finally:
            cam.close()
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true", help="32 lines instead of 128")
    ap.add_argument("--size", type=int, default=None, help="lines (and samples) per scan")
    ap.add_argument("--time-ms", type=float, default=1.0, help="integration time (default 1 ms)")
    ap.add_argument("--oversample", type=float, default=2.0, help="frames per line (default 2)")
    args = ap.parse_args()
    size = args.size or (32 if args.quick else 128)

    from mehs.capture.aravis import aravis_available

    rows = []
    proc, urls = start_sim(size)
    try:
        for mode, secs, info in measure(urls, size, args.time_ms, args.oversample):
            rows.append(("serial (TCP)", mode, secs, info))
    finally:
        proc.terminate()
        proc.wait()
    why = aravis_available()
    if why is None:
        proc, urls = start_sim(size, "--genicam")
        try:
            for mode, secs, info in measure(urls, size, args.time_ms, args.oversample):
                rows.append(("GigE Vision (Aravis)", mode, secs, info))
        finally:
            proc.terminate()
            proc.wait()
    ref = next(size / s for p, m, s, _ in rows if p.startswith("serial") and m == "continuous")
    print(f"{size} lines × {size} samples × 204 bands, {args.time_ms:g} ms, oversample {args.oversample:g}; "
          f"reference = serial continuous ({ref:.1f} lines/s)")
    print(f"{'camera path':22s} {'scan':11s} {'s':>7s} {'lines/s':>9s} {'× ref':>7s}  frames/line  frame Hz")
    for path, mode, secs, info in rows:
        lps = size / secs
        print(f"{path:22s} {mode:11s} {secs:7.2f} {lps:9.1f} {lps / ref:7.2f}  "
              f"{info.get('frames_per_line', ''):>11}  {info.get('frame_rate_hz', '')}")
    if why is not None:
        print(f"(GigE Vision rows skipped: {why})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
