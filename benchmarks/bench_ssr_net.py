"""Conversion time of the SSR networks on a 2048×1024 HDR image on the CPU, beside Smits 1999.

    python benchmarks/bench_ssr_net.py [--quick] [--size small|tiny|full] [--threads N] [--no-onnx]

Reference measured in the same run: the vectorised Smits 1999 baseline
(``mehs.ssr.baselines.Smits1999``). Paper figures (CPU i9-11900, 2048×1024):
Smits 0.788 s, the proposed network 16.3 s. Timings are of the full model call
(linear RGB in, 31-band spectra out, luminance restored), best of ``--repeat``
after a warm-up on a small crop. The networks' weights are random: the time does
not depend on them. ``--quick`` uses a 512×256 image.
"""

from __future__ import annotations

import argparse


from _timing import best_time
from mehs.ssr.timing import PAPER_SECONDS as _PAPER, synthetic_timing_image

#: Paper Table 5, CPU column (i9-11900, 2048×1024)
PAPER_SECONDS = {name: cpu for name, (cpu, _gpu) in _PAPER.items()}



def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--quick", action="store_true", help="512×256 instead of 2048×1024")
    ap.add_argument("--size", default="small", help="zoo preset (--preset of mehs train-ssr)")
    ap.add_argument("--repeat", type=int, default=1)
    ap.add_argument("--threads", type=int, default=0, help="torch threads (0: torch's default)")
    ap.add_argument("--no-onnx", dest="onnx", action="store_false",
                    help="skip the onnxruntime timings of the exported graphs")
    args = ap.parse_args(argv)

    import tempfile
    from pathlib import Path

    import torch

    from mehs.ssr.baselines import Smits1999
    from mehs.ssr.net.zoo import ARCHITECTURES
    from mehs.ssr.net.export import TorchSSRModel, export_onnx

    if args.threads:
        torch.set_num_threads(args.threads)
    h, w = (256, 512) if args.quick else (1024, 2048)
    rgb = synthetic_timing_image((h, w))
    torch.manual_seed(0)
    rows = [("smits", "Smits 1999 (vectorised numpy)", Smits1999())]
    nets = {}
    # the paper's net, and the FC-DenseNet end to end (the attention variant format 1
    # called "fcdensenet"); bench_ssr_zoo.py times every architecture
    for variant, make in (("hdrssr", lambda: ARCHITECTURES["hdrssr"](args.size)),
                          ("fcdensenet", lambda: ARCHITECTURES["galliani"](
                              args.size, mode="e2e", params={"attention": True, "dropout": 0.0}))):
        net = make()
        nets[variant] = net
        n_par = sum(p.numel() for p in net.parameters())
        rows.append((variant, f"{variant} torch ({args.size}, {n_par / 1e3:.0f} k params)",
                     TorchSSRModel(net)))
    tmp = tempfile.TemporaryDirectory()
    if args.onnx:
        try:
            from mehs.ssr.models import OnnxModel

            for variant, net in nets.items():
                path = export_onnx(net, Path(tmp.name) / f"{variant}.onnx")
                rows.append((variant, f"{variant} ONNX (onnxruntime CPU)", OnnxModel(path)))
        except ImportError as exc:  # onnxruntime is an optional extra
            print(f"(ONNX rows skipped: {exc})")

    print(f"SSR conversion time, {w}×{h} linear HDR RGB → 31 bands, CPU, "
          f"torch {torch.__version__}, {torch.get_num_threads()} threads")
    results = []
    for key, label, model in rows:
        results.append((key, label, best_time(model, rgb, args.repeat)))
    ref = results[0][2]
    scale = (2048 * 1024) / (w * h)
    print(f"{'method':<44} {'seconds':>9} {'× Smits':>8} {'paper s':>8} {'vs paper':>9}")
    for key, label, sec in results:
        paper = PAPER_SECONDS.get(key) if "ONNX" not in label else None
        vs = f"{paper / (sec * scale):.2f}×" if paper else ""
        print(f"{label:<44} {sec:9.3f} {sec / ref:8.1f} "
              f"{paper if paper else '':>8} {vs:>9}")
    if args.quick:
        print("(--quick: 'vs paper' extrapolates linearly to 2048×1024)")
    print("'vs paper' > 1 means faster than the paper's figure (its CPU: i9-11900).")
    tmp.cleanup()
    return 0


if __name__ == "__main__":
    from _load import run_reporting_load  # the load this run saw (issue 16)

    run_reporting_load(main)
