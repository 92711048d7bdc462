"""Dataset build benchmark: one full-size scene (3 × 512×512×204, 12-bit) → dataset entry.

Measured side by side in one run (design.md §7, target ≤ 5 s per scene):

1. **stages run separately** in this process, the same calls the builder makes:
   hash (inputs for the scene key, checked against scene.json, and outputs for the
   manifest), read (``load_bracket``), response + merge +
   ghosts (``fuse_bracket``; its own breakdown), resample to 31 bands, RGB
   (``hdr_rgb``, ``ldr_rgb``, preview tone map), write (ENVI, EXR, PNGs,
   response and summary JSON);
2. **the build**: ``mehs.dataset.build.build_dataset([scene], out, workers=1)`` in a
   fresh child process (numba kernels warmed on a tiny scene first, as in a
   long build), with its per-stage breakdown from the manifest's provenance
   and the child's peak resident memory.

The ratio build / sum-of-stages is the orchestration overhead (manifest,
atomic commit, bookkeeping).

Usage: ``python benchmarks/bench_build.py [--quick] [--size N] [--response auto|linear]``
(``--quick``: 128×128 scene).
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

TIMES_MS = (0.05, 0.4, 3.2)


def make_scene(folder: Path, size: int, seed: int = 1) -> Path:
    from mehs.capture.scene import make_scene as mk
    from mehs.capture.sensor import SensorModel
    from mehs.capture.simulate import simulate_bracket, write_simulated_scene

    sim = simulate_bracket(mk("window", size, size, seed=seed), SensorModel(seed=3), TIMES_MS,
                           seed=0)
    return write_simulated_scene(sim, folder, scene_id=folder.name)


def warm_up(tmp: Path, response: str) -> None:
    """Compile the numba kernels on a tiny scene so that no stage pays for JIT."""
    from mehs.dataset.build import build_dataset

    small = make_scene(tmp / "warm", 16, seed=2)
    build_dataset([small], tmp / "warm_ds", workers=1, progress=False,
                  response=_curve(tmp, response))


def _curve(tmp: Path, response: str):
    if response == "auto":
        return None
    from mehs.synthesis.response import ResponseCurve

    path = tmp / "linear.json"
    if not path.exists():
        ResponseCurve.linear(12).save(path)
    return path


def stages_separately(scene: Path, out: Path, response: str) -> dict[str, float]:
    import numpy as np

    from mehs.dataset.build import input_files, to_31_bands
    from mehs.io.atomic import sha256_files, write_json_atomic
    from mehs.io.envi import write_envi
    from mehs.io.exr import write_exr_rgb
    from mehs.preview import tonemap, write_png
    from mehs.rgb import WAVELENGTHS_31, hdr_rgb, ldr_rgb
    from mehs.synthesis.bracket import load_bracket
    from mehs.synthesis._ranges import thread_count
    from mehs.synthesis.fuse import fuse_bracket

    t: dict[str, float] = {}
    out.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    # as the builder does: side by side on the merge's threads
    sha256_files(input_files(_Src(scene)), threads=thread_count())
    t["hash"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    # as the builder does: the input hashes above are the verification
    bracket = load_bracket(scene, verify="size")
    t["read"] = time.perf_counter() - t0
    curve = _curve(out.parent, response)
    t0 = time.perf_counter()
    res = fuse_bracket(bracket, method="poisson", response=str(curve) if curve else "auto",
                       ghosts="detect", seed=0)
    t["fuse"] = time.perf_counter() - t0
    for k, v in res.summary.pop("timings").items():
        if k != "total_s":
            t[f"fuse.{k[:-2]}"] = v
    del bracket
    t0 = time.perf_counter()
    hs = to_31_bands(res.radiance)
    data = np.ascontiguousarray(hs.data, dtype=np.float32)
    t["resample"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    hdr = hdr_rgb(data, WAVELENGTHS_31)
    scale = np.float32(0.5 ** max(0, int(np.ceil(np.log2(max(hdr.max(), 1) / 65504)))))
    data, hdr = data * scale, hdr * scale
    ldr, _ = ldr_rgb(hdr)
    prev = tonemap(hdr)
    t["rgb"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    written: dict[str, str] = {}        # the cube hashed as it is written, as the builder does
    write_envi(out / "hs.hdr", hs.with_data(data, metadata={}), dtype=np.float32,
               data_ext=".dat", sha256=written)
    write_exr_rgb(out / "hdr_rgb.exr", hdr, half=True)
    write_png(out / "ldr_rgb.png", ldr)
    write_png(out / "mask.png", res.mask)
    write_png(out / "preview.png", prev)
    res.response.save(out / "response.json")
    write_json_atomic(out / "fusion.json", res.summary)
    t["write"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    sha256_files({f.name: f for f in out.iterdir() if f.name not in written},
                 threads=thread_count())
    t["hash"] += time.perf_counter() - t0
    return t


class _Src:
    kind = "scene"

    def __init__(self, scene: Path):
        self.paths = (str(scene),)


def child(scene: str, out: str, response: str) -> None:
    """Run in a fresh process: warm up, then time one build; print JSON."""
    from mehs.dataset.build import build_dataset
    from mehs.dataset.manifest import read_manifest

    tmp = Path(out).parent
    warm_up(tmp, response)
    base_mb = _rss_mb()
    t0 = time.perf_counter()
    build_dataset([scene], out, workers=1, progress=False, response=_curve(tmp, response))
    wall = time.perf_counter() - t0
    (entry,) = read_manifest(out)["scenes"]
    print(json.dumps({"wall": wall, "stages": entry["provenance"]["run"]["stage_seconds"],
                      "status": entry["status"], "reasons": entry["reasons"],
                      "base_mb": base_mb,
                      "maxrss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024}))


def _rss_mb() -> float:
    """Current resident set size (Linux /proc), MB."""
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024
    return float("nan")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="128×128 scene")
    ap.add_argument("--size", type=int, default=None)
    ap.add_argument("--response", choices=["auto", "linear"], default="auto")
    ap.add_argument("--child", nargs=3, metavar=("SCENE", "OUT", "RESPONSE"),
                    help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.child:
        child(*args.child)
        return 0
    size = args.size or (128 if args.quick else 512)
    with tempfile.TemporaryDirectory(prefix="bench_build_") as d:
        tmp = Path(d)
        t0 = time.perf_counter()
        scene = make_scene(tmp / "scene", size)
        print(f"scene: 3 × {size}×{size}×204 uint16 (simulated in {time.perf_counter() - t0:.1f} s), "
              f"response={args.response}")
        stack_mb = 3 * size * size * 204 * 2 / 2**20

        proc = subprocess.run([sys.executable, __file__, "--child", str(scene),
                               str(tmp / "ds"), args.response],
                              capture_output=True, text=True, cwd=ROOT)
        if proc.returncode:
            print(proc.stderr, file=sys.stderr)
            return 1
        b = json.loads(proc.stdout.strip().splitlines()[-1])

        (tmp / "sep").mkdir()
        warm_up(tmp / "sep", args.response)
        sep = stages_separately(scene, tmp / "sep" / "out", args.response)

    order = ["hash", "read", "fuse", "fuse.response", "fuse.merge", "fuse.ghosts",
             "resample", "rgb", "write"]
    print(f"\n{'stage':<16}{'separately s':>14}{'in build s':>12}")
    for k in order:
        a, c = sep.get(k), b["stages"].get(k)
        print(f"{k:<16}{'' if a is None else f'{a:.3f}':>14}{'' if c is None else f'{c:.3f}':>12}")
    total_sep = sum(v for k, v in sep.items() if "." not in k)
    print(f"{'total':<16}{total_sep:>14.3f}{b['wall']:>12.3f}")
    print(f"\nbuild one scene: {b['wall']:.2f} s  (target ≤ 5 s: "
          f"{'PASS' if b['wall'] <= 5 else 'FAIL'}); ratio build / sum of stages run "
          f"separately = {b['wall'] / total_sep:.2f}×")
    grow = b["maxrss_mb"] - b["base_mb"]
    print(f"peak RSS of the build process: {b['maxrss_mb']:.0f} MB; above the {b['base_mb']:.0f} MB "
          f"held before the build (imports, warm-up): {grow:.0f} MB = "
          f"{grow / stack_mb:.2f}× the raw stack ({stack_mb:.0f} MB)")
    print(f"scene status: {b['status']} {b['reasons']}")
    print(f"load average during the run: {' '.join(f'{x:.1f}' for x in os.getloadavg())} "
          f"on {os.cpu_count()} CPUs (timings are only meaningful on a quiet machine)")
    return 0


if __name__ == "__main__":
    from _load import load_line  # the load this run saw (issue 16)

    parent = "--child" not in sys.argv     # the child's stdout is one line of JSON
    if parent:
        print("before:", load_line(), flush=True)
    rc = main()
    if parent:
        print("after: ", load_line())
    sys.exit(rc)
