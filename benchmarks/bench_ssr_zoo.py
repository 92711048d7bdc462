"""Conversion time of every SSR zoo architecture (full preset) on a 2048×1024 HDR image
on the CPU, beside Smits 1999 measured in the same run (the paper's Table 5).

    python benchmarks/bench_ssr_zoo.py [--quick] [--archs hdrssr,mstpp,...] [--preset full]
                                       [--threads N] [--repeat 1] [--tile 512]

Reference measured in the same run: the vectorised Smits 1999 baseline
(``mehs.ssr.baselines.Smits1999``). Paper figures (CPU i9-11900, 2048×1024, mean of
ten images): Smits 0.788 s, ours 16.3 s, Mikamoto 14.8 s, Galliani 6.3 s, HSCNN-D
52.0 s, AWAN 324.6 s. Each network is timed from linear RGB to 31-band spectra
(pre-processing and, in the similarity mode, luminance restoration included),
best of ``--repeat`` after a warm-up on a small crop. Weights are random: the time
does not depend on them. Networks with image-wide operations run on the whole
image, as their authors run them; HSCNN-D too, streamed down its rows (session 29:
a window of 63 rows of its 1088 dense channels, 0.56 GB, where the image's needed
~9 GB and was cut into exact tiles of ``--tile`` pixels). AWAN
cannot run whole at 2048×1024 (its non-local affinity has 2.7·10¹¹ entries per
quadrant, ~1 TB): it runs in ``--tile`` tiles, each an image of its own (at 512 the
size its authors ran it at, 482×512), marked "approx." (``--approx`` names the
architectures treated so).
``--quick`` uses a 512×256 image and extrapolates the "vs paper" column linearly
(AWAN's non-local block is quadratic in the pixels, so its extrapolation is a
lower bound).
"""

from __future__ import annotations

import argparse

import numpy as np

from _timing import best_time
from mehs.ssr.timing import PAPER_SECONDS as _PAPER, synthetic_timing_image

#: Paper Table 5, CPU column (i9-11900, 2048×1024)
PAPER_SECONDS = {name: cpu for name, (cpu, _gpu) in _PAPER.items()}



def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--quick", action="store_true", help="512×256 instead of 2048×1024")
    ap.add_argument("--archs", default="", help="comma-separated subset (default: all)")
    ap.add_argument("--preset", default="full", help="zoo preset (default full)")
    ap.add_argument("--repeat", type=int, default=1)
    ap.add_argument("--threads", type=int, default=0, help="torch threads (0: torch's default)")
    ap.add_argument("--tile", type=int, default=512, help="tile side for local networks")
    ap.add_argument("--approx", default="awan",
                    help="architectures run in plain tiles although not local (default awan)")
    args = ap.parse_args(argv)

    import torch

    from mehs.ssr.baselines import Smits1999
    from mehs.ssr.net.base import count_parameters
    from mehs.ssr.net.infer import predict_tiled
    from mehs.ssr.net.zoo import ARCHITECTURES

    if args.threads:
        torch.set_num_threads(args.threads)
    h, w = (256, 512) if args.quick else (1024, 2048)
    rgb = synthetic_timing_image((h, w))
    names = [a for a in args.archs.split(",") if a] or list(ARCHITECTURES)

    smits = Smits1999()
    rows = [("smits", "Smits 1999 (vectorised numpy)", best_time(smits, rgb, args.repeat))]
    for name in names:
        torch.manual_seed(0)
        net = ARCHITECTURES[name](args.preset).eval()

        # (a network streaming its rows holds a window, not the image: whole)
        streams = bool(getattr(net, "stream_window_rows", lambda width: 0)(w))
        tile = max(h, w) if streams else args.tile

        @torch.no_grad()
        def run(x, net=net, approx=name in args.approx.split(","), tile=tile):
            t = torch.from_numpy(np.ascontiguousarray(x.transpose(2, 0, 1))[None])
            return predict_tiled(net, t, tile=tile, approximate=approx)[0] \
                .permute(1, 2, 0).numpy()

        approx = name in args.approx.split(",")
        label = f"{name} ({args.preset}, {count_parameters(net) / 1e6:.2f} M)"
        if max(h, w) > tile and (net.receptive_radius is not None or approx):
            label += f", tiles {args.tile}" + (" approx." if net.receptive_radius is None else "")
        rows.append((name, label, best_time(run, rgb, args.repeat)))
        print(f"  {label}: {rows[-1][2]:.2f} s", flush=True)
        del net

    print(f"\nSSR conversion time, {w}×{h} linear HDR RGB → 31 bands, CPU, "
          f"torch {torch.__version__}, {torch.get_num_threads()} threads")
    ref = rows[0][2]
    scale = (2048 * 1024) / (w * h)
    print(f"| {'method':<40} | {'seconds':>9} | {'× Smits':>8} | {'paper s':>8} | "
          f"{'paper × Smits':>13} |")
    print(f"|{'-' * 42}|{'-' * 10}:|{'-' * 9}:|{'-' * 9}:|{'-' * 14}:|")
    for key, label, sec in rows:
        paper = PAPER_SECONDS.get(key)
        pr = f"{paper / PAPER_SECONDS['smits']:.1f}" if paper else ""
        print(f"| {label:<40} | {sec:9.3f} | {sec / ref:8.1f} | "
              f"{paper if paper else '':>8} | {pr:>13} |")
    if args.quick:
        print(f"(--quick: the paper's figures are for 2048×1024, {scale:.0f}× more pixels)")
    print("'× Smits' is the ratio to Smits measured in this run; compare it with the paper's "
          "ratio (its CPU: i9-11900).")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
