"""Peak memory and time of SSR network inference, whole image vs tiles (issue 16).

    python benchmarks/bench_ssr_tiling.py [--quick] [--variant hdrssr] [--onnx] [--budget MiB]
                                          [--cap GB] [--repeat N] [--statistics auto|tile|image]

Each configuration runs in its own child process (peak RSS is per process):
the model is built with fixed seeds, warmed on a 64×64 crop, then converts
one 2048×1024 linear RGB image (``--quick``: 1024×512) once. The child reports
the wall time of that call (for tiles: the memory and margin probes included,
and also shown apart) and its peak resident memory (``ru_maxrss``, which
includes the Python, torch and numpy start-up, the input and the output), and
saves the output; the parent compares tiled with whole-image outputs (median
and maximum relative difference). Whole-image inference is the reference
measured in the same run; ``--repeat N`` alternates the two children N times
and shows median times and the highest peak (CPU seconds are shown too, but
OpenMP threads spinning for a CPU another process holds inflate them).

The probes are cached per architecture (``mehs.ssr.probe_cache``): the parent gives the
children a fresh cache folder, so the first tiled process measures them and later ones
read them; the row "tiled" is the median of those later ones (with ``--repeat`` > 1) and
the first is shown apart. ``--no-probe-cache``: every process measures.

Targets (issue 16): tiled peak RSS ≤ 2 GB, time within 10 % of whole-image.
Since the networks' inference runs in row strips (session 23), the small preset's
2048×1024 image fits the 2 GB cap whole (~1.4 GB), so the library runs it untiled
and the verdict says so; ``--size full`` (the published FC-DenseNet56 size) or
``--budget`` show the tiles' cost.
The tiled run uses the library's default budget (``mehs.ssr.tiling.DEFAULT_MAX_RSS``,
2 GB of resident memory for the whole process); ``--quick`` caps the process at
1 GB instead, so that its smaller image (whole: ~1.0 GB) is tiled too, and
checks against that cap.

The networks are the untrained mehs ones (random weights: the time and
memory do not depend on them). Their channel attention takes means over the
whole input; by default the tiles run with the whole image's means
(:mod:`mehs.ssr.tiling_global`: one more, partial run over the tiles), which equal
whole-image inference to float rounding; ``--statistics tile`` gives each tile its own
(faster; the output then differs from the whole image's by that, not by seams).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent))
sys.path.insert(0, str(HERE))


def child(args) -> None:
    import resource
    import time

    import torch

    from mehs.ssr.net.zoo import build_network
    from mehs.ssr.timing import synthetic_timing_image
    from mehs.ssr.net.export import TorchSSRModel, export_onnx

    h, w = args.shape
    torch.manual_seed(0)
    net = build_network(arch=args.variant, preset=args.size)
    if args.onnx:
        from mehs.ssr.models import OnnxModel

        model = OnnxModel(export_onnx(net, Path(args.out).with_suffix(".onnx")))
    else:
        model = TorchSSRModel(net)
    from mehs.ssr import tiling

    opts = {} if args.budget is None else {"max_bytes": int(args.budget * 2**20)}
    if args.statistics != "auto":
        opts["statistics"] = args.statistics
    if args.cap is not None and int(args.cap * 1e9) != tiling.DEFAULT_MAX_RSS:
        opts["max_rss"] = int(args.cap * 1e9)
    rgb = synthetic_timing_image((h, w))
    model.tiling = "off"                   # the warm-up runs no probe in either mode
    model(rgb[:64, :64])
    model.tiling = "off" if args.mode == "whole" else (opts or "auto")
    base = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024
    if hasattr(model, "standard_spectrum"):
        # the network's own output is kept (untimed) for the comparison: luminance
        # restoration divides by its X+Y+Z, which magnifies float rounding where that is
        # near 0, so the restored spectra alone would not show what the tiles changed
        from mehs.ssr.luminance import restore_luminance

        t0, c0 = time.perf_counter(), time.process_time()
        y = model.standard_spectrum(rgb)
        sec, cpu = time.perf_counter() - t0, time.process_time() - c0
        np.save(Path(args.out).with_suffix(".net.npy"), y)
        t0, c0 = time.perf_counter(), time.process_time()
        if model.restores_luminance:
            y = restore_luminance(y, rgb, model.wavelengths, overwrite=True)
        sec, cpu = sec + time.perf_counter() - t0, cpu + time.process_time() - c0
    else:
        t0, c0 = time.perf_counter(), time.process_time()
        y = model(rgb)
        sec, cpu = time.perf_counter() - t0, time.process_time() - c0
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024
    np.save(args.out, y)
    probe = getattr(model, "_tiling_probe", None)
    last = dict(getattr(model, "_tiling_last", None) or {})
    last.pop("plan", None)
    print(json.dumps({"seconds": sec, "cpu": cpu, "peak": peak, "before": base, "probe": probe,
                      "last": last, "threads": torch.get_num_threads()}))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--quick", action="store_true", help="1024×512 instead of 2048×1024")
    ap.add_argument("--variant", default="hdrssr", help="zoo architecture (--arch of mehs train-ssr)")
    ap.add_argument("--size", default="small", help="zoo preset (--preset of mehs train-ssr)")
    ap.add_argument("--onnx", action="store_true", help="run the exported ONNX graph instead")
    ap.add_argument("--budget", type=float, default=None,
                    help="MiB for one tile (default: the library's choice from the cap)")
    ap.add_argument("--cap", type=float, default=None,
                    help="peak RSS of the process in GB the default budget keeps under "
                         "(default 2, --quick 1)")
    ap.add_argument("--repeat", type=int, default=1,
                    help="run the two children this many times, alternating; median times "
                         "(a busy machine's load drifts between runs)")
    ap.add_argument("--no-probe-cache", action="store_true",
                    help="every tiled process measures its probes (default: the first one "
                         "does, into a fresh cache folder, and later ones read them)")
    ap.add_argument("--statistics", choices=("auto", "tile", "image"), default="auto",
                    help="global-pooling means: the library's default (auto: the whole "
                         "image's where the network allows), each tile's, or the image's")
    ap.add_argument("--child", choices=("whole", "tiled"), dest="mode", default=None)
    ap.add_argument("--out", default=None)
    ap.add_argument("--shape", type=int, nargs=2, default=None)
    args = ap.parse_args(argv)
    if args.mode:
        child(args)
        return 0
    from _load import load_line

    shape = (512, 1024) if args.quick else (1024, 2048)
    if args.cap is None:
        args.cap = 1.0 if args.quick else 2.0
    tmp = Path(tempfile.mkdtemp(prefix="mehs_bench_tiling_"))
    # a fresh probe cache: the first tiled process measures, the later ones read
    env = dict(os.environ, PYTHONPATH=str(HERE.parent),
               MEHS_CACHE_DIR="" if args.no_probe_cache else str(tmp / "cache"))
    res = {}
    print(load_line())
    runs = {"tiled": [], "whole": []}
    for _ in range(max(1, args.repeat)):
        for mode in ("tiled", "whole"):
            out = tmp / f"{mode}.npy"
            cmd = [sys.executable, __file__, "--child", mode, "--out", str(out), "--variant",
                   args.variant, "--size", args.size, "--shape", *map(str, shape)]
            if args.onnx:
                cmd.append("--onnx")
            if args.budget is not None:
                cmd += ["--budget", str(args.budget)]
            cmd += ["--cap", str(args.cap), "--statistics", args.statistics]
            r = subprocess.run(cmd, capture_output=True, text=True, env=env)
            if r.returncode:
                print(f"{mode}: child failed\n{r.stderr[-2000:]}")
                return 1
            runs[mode].append(json.loads(r.stdout.strip().splitlines()[-1]))
    first = runs["tiled"][0]
    if not args.no_probe_cache and len(runs["tiled"]) > 1:
        runs["tiled"] = runs["tiled"][1:]          # the median of the processes that read
    for mode, rs in runs.items():
        res[mode] = dict(rs[-1], out=tmp / f"{mode}.npy", peak=max(r["peak"] for r in rs),
                         seconds=float(np.median([r["seconds"] for r in rs])),
                         cpu=float(np.median([r["cpu"] for r in rs])))
    res["tiled"]["peak"] = max(res["tiled"]["peak"], first["peak"])
    print(load_line())
    a = np.load(res["tiled"]["out"], mmap_mode="r")
    b = np.load(res["whole"]["out"], mmap_mode="r")
    scale = float(np.abs(b).max())
    rel = np.abs(a - b) / scale
    what = f"{args.variant} {'ONNX' if args.onnx else 'torch'} ({args.size})"
    t = res["tiled"]
    probe = {k: (round(v) if isinstance(v, float) else v) for k, v in (t["probe"] or {}).items()}
    print(f"SSR network {what}, {shape[1]}×{shape[0]} → 31 bands; "
          f"torch threads {res['whole']['threads']}; tiling probe {probe}; "
          f"pooling means: {args.statistics} → {t['last'].get('statistics', 'whole image')}"
          + (f"; median of {args.repeat} alternating runs" if args.repeat > 1 else ""))
    summary = t["last"].get("summary") or {"tile": shape, "tiles": 1, "computed": 1.0}
    plan = (f"{summary['tile'][1]}×{summary['tile'][0]} × {summary['tiles']}, "
            f"{summary['computed']:.3f}× px"
            + (", tiles on the reused C heap" if t["last"].get("heap_reuse") else "")
            + (f", {t['last']['image_runs']} runs for image-wide means"
               if t["last"].get("image_runs") else "")
            + (f", heap returned before {t['last']['heap_trims']} tiles (budget short)"
               if t["last"].get("heap_trims") else ""))
    budget = t["last"].get("budget")
    print(f"{'mode':<6} {'seconds':>8} {'× whole':>8} {'CPU s':>7} {'× whole':>8} "
          f"{'peak RSS GB':>12} {'before GB':>10} {'probes s':>9}  "
          "plan (tile w×h × tiles, pixels computed / image)")
    ratio = t["seconds"] / res["whole"]["seconds"]
    rows = [("whole", res["whole"]), ("tiled", t)]
    if not args.no_probe_cache and args.repeat > 1:
        rows.append(("tiled, first process (probes measured)", first))
    for label, r in rows:
        extra = (f"{r['last'].get('probe_seconds', 0.0):9.2f}  {plan}" if label != "whole"
                 else f"{'':9}  {shape[1]}×{shape[0]} × 1, 1.000× px")
        print(f"{label:<6} {r['seconds']:8.2f} {r['seconds'] / res['whole']['seconds']:7.2f}× "
              f"{r['cpu']:7.2f} {r['cpu'] / res['whole']['cpu']:7.2f}× "
              f"{r['peak'] / 1e9:12.2f} {r['before'] / 1e9:10.2f} {extra}")
    if not args.no_probe_cache:
        print("tiled: " + ("processes after the first, which read the probes from the cache"
                           if args.repeat > 1 else "one process, which measured the probes"))
    if budget is not None and args.budget is not None:
        print(f"budget for one tile {budget / 1e9:.2f} GB (--budget)")
    elif budget is not None:
        print(f"budget for the inference {budget / 1e9:.2f} GB (cap {args.cap:g} GB less what "
              f"the process held), of which the stitched output "
              f"{t['last'].get('out_bytes', 0) / 1e9:.2f} GB")
    print(f"tiled vs whole, |Δ| / max|whole|: median {np.median(rel):.2e}, max {rel.max():.2e}"
          " (the model's output)")
    net_out = [res[m]["out"].with_suffix(".net.npy") for m in ("tiled", "whole")]
    if all(p.exists() for p in net_out):
        a = np.load(net_out[0], mmap_mode="r")
        b = np.load(net_out[1], mmap_mode="r")
        rel = np.abs(a - b) / float(np.abs(b).max())
        print(f"tiled vs whole, |Δ| / max|whole|: median {np.median(rel):.2e}, max "
              f"{rel.max():.2e} (the network's output, before luminance restoration)")
    rss_ok = t["peak"] <= args.cap * 1e9
    time_ok = ratio <= 1.10
    print(f"verdict: tiled peak RSS {t['peak'] / 1e9:.2f} GB ≤ {args.cap:g} GB: "
          f"{'met' if rss_ok else 'NOT met'}; tiled time {ratio:.2f}× ≤ 1.10× whole: "
          f"{'met' if time_ok else 'NOT met'}"
          + ("" if res["whole"]["peak"] > args.cap * 1e9 else
             f" (whole image {res['whole']['peak'] / 1e9:.2f} GB fits the cap: tiling not needed)"))
    import shutil

    shutil.rmtree(tmp)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
