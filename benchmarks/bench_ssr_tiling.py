"""Peak memory and time of SSR network inference, whole image vs tiles (issue 16).

    python benchmarks/bench_ssr_tiling.py [--quick] [--variant hdrssr] [--onnx] [--budget MiB]

Each configuration runs in its own child process (peak RSS is per process):
the model is built with fixed seeds, warmed on a 64×64 crop, then converts
one 2048×1024 linear RGB image (``--quick``: 1024×512) once. The child reports
the wall time of that call and its peak resident memory (``ru_maxrss``, which
includes the Python, torch and numpy start-up, the input and the output), and
saves the output; the parent compares tiled with whole-image outputs (median
and maximum relative difference, over the whole image and away from the tile
seams). Whole-image inference is the reference measured in the same run.
Targets (issue 16): tiled peak RSS ≤ 2 GB, time within 10 % of whole-image.

The networks are the untrained mehs ones (random weights: the time and
memory do not depend on them). Their channel attention takes means over the
whole input, so tiles differ from the whole image by that, not by seams.
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
    opts = {} if args.budget is None else {"max_bytes": int(args.budget * 2**20)}
    model.tiling = "off" if args.mode == "whole" else (opts or "auto")
    rgb = synthetic_timing_image((h, w))
    model(rgb[:64, :64])
    base = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024
    t0 = time.perf_counter()
    y = model(rgb)
    sec = time.perf_counter() - t0
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024
    np.save(args.out, y)
    probe = getattr(model, "_tiling_probe", None)
    print(json.dumps({"seconds": sec, "peak": peak, "before": base,
                      "probe": probe, "threads": torch.get_num_threads()}))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--quick", action="store_true", help="1024×512 instead of 2048×1024")
    ap.add_argument("--variant", default="hdrssr", help="zoo architecture (--arch of mehs train-ssr)")
    ap.add_argument("--size", default="small", help="zoo preset (--preset of mehs train-ssr)")
    ap.add_argument("--onnx", action="store_true", help="run the exported ONNX graph instead")
    ap.add_argument("--budget", type=float, default=None,
                    help="MiB for one tile (default: the library's choice from free memory)")
    ap.add_argument("--child", choices=("whole", "tiled"), dest="mode", default=None)
    ap.add_argument("--out", default=None)
    ap.add_argument("--shape", type=int, nargs=2, default=None)
    args = ap.parse_args(argv)
    if args.mode:
        child(args)
        return 0
    from _load import load_line

    shape = (512, 1024) if args.quick else (1024, 2048)
    tmp = Path(tempfile.mkdtemp(prefix="mehs_bench_tiling_"))
    env = dict(os.environ, PYTHONPATH=str(HERE.parent))
    res = {}
    print(load_line())
    for mode in ("tiled", "whole"):
        out = tmp / f"{mode}.npy"
        cmd = [sys.executable, __file__, "--child", mode, "--out", str(out), "--variant",
               args.variant, "--size", args.size, "--shape", *map(str, shape)]
        if args.onnx:
            cmd.append("--onnx")
        if args.budget is not None:
            cmd += ["--budget", str(args.budget)]
        r = subprocess.run(cmd, capture_output=True, text=True, env=env)
        if r.returncode:
            print(f"{mode}: child failed\n{r.stderr[-2000:]}")
            return 1
        res[mode] = json.loads(r.stdout.strip().splitlines()[-1])
        res[mode]["out"] = out
    print(load_line())
    a = np.load(res["tiled"]["out"], mmap_mode="r")
    b = np.load(res["whole"]["out"], mmap_mode="r")
    scale = float(np.abs(b).max())
    rel = np.abs(a - b) / scale
    what = f"{args.variant} {'ONNX' if args.onnx else 'torch'} ({args.size})"
    print(f"SSR network {what}, {shape[1]}×{shape[0]} → 31 bands; "
          f"torch threads {res['whole']['threads']}; tiling probe {res['tiled']['probe']}")
    print(f"{'mode':<8} {'seconds':>8} {'× whole':>8} {'peak RSS GB':>12} {'before call GB':>15}")
    for mode in ("whole", "tiled"):
        r = res[mode]
        print(f"{mode:<8} {r['seconds']:8.2f} {r['seconds'] / res['whole']['seconds']:7.2f}× "
              f"{r['peak'] / 1e9:12.2f} {r['before'] / 1e9:15.2f}")
    print(f"tiled vs whole, |Δ| / max|whole|: median {np.median(rel):.2e}, max {rel.max():.2e}")
    print("targets (issue 16): tiled peak RSS ≤ 2 GB; tiled time ≤ 1.10× whole")
    for p in tmp.iterdir():
        p.unlink()
    tmp.rmdir()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
