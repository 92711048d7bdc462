"""Every registered SSR architecture at 2048×1024 on the CPU, ratio to Smits 1999 in the same run.

    python benchmarks/bench_ssr_archs.py [--quick] [--preset full|small|tiny] [--arch NAME ...]

Driven by the model registry (``mehs.ssr.registry.ARCHITECTURES``), so the
architectures of the model zoo show up without editing this file. For each one:
parameters of the chosen preset (beside the published count of the full preset
when the architecture records it, and the deviation), and the time of the full
model call (linear RGB in, 31-band spectra out, luminance restored for ◇ networks),
best of ``--repeat`` after a warm-up on a 16×16 crop. Reference measured in the
same run: the vectorised Smits 1999 (``mehs.ssr.baselines.Smits1999``). Weights
are random: the time does not depend on them. Paper (CPU i9-11900, 2048×1024):
Smits 0.788 s, the proposed network 16.3 s, AWAN 324.6 s. ``--quick``: 512×256.
"""

from __future__ import annotations

import argparse

import numpy as np


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--quick", action="store_true", help="512×256 instead of 2048×1024")
    ap.add_argument("--preset", default=None,
                    help="preset of every architecture (default: full, else its first preset)")
    ap.add_argument("--arch", action="append", default=None, help="only this architecture")
    ap.add_argument("--repeat", type=int, default=1)
    ap.add_argument("--threads", type=int, default=0, help="torch threads (0: torch's default)")
    args = ap.parse_args(argv)

    import torch

    from mehs.ssr.baselines import Smits1999
    from mehs.ssr.net.export import TorchSSRModel
    from mehs.ssr.registry import list_architectures
    from mehs.ssr.scoring import PAPER_SECONDS, time_models

    if args.threads:
        torch.set_num_threads(args.threads)
    shape = (256, 512) if args.quick else (1024, 2048)
    archs = list_architectures()
    if args.arch:
        archs = {k: v for k, v in archs.items() if k in args.arch}
    models, info = [(Smits1999(), "smits")], {"smits": (0, None, "-")}
    for name, arch in archs.items():
        preset = args.preset or ("full" if "full" in arch.presets else next(iter(arch.presets), None))
        cfg = dict(arch.presets.get(preset, {})) if preset else {}
        torch.manual_seed(0)
        net = arch.build(cfg)
        n = sum(p.numel() for p in net.parameters())
        models.append((TorchSSRModel(net, name=name, arch=name), name))
        info[name] = (n, arch.published_params, preset)
    rows = time_models(models, shape=shape, repeat=args.repeat, devices=("cpu",))
    ref = next(r["seconds"] for r in rows if r["model"] == "smits")
    print(f"# SSR architectures, {shape[1]}×{shape[0]} image, CPU "
          f"({torch.get_num_threads()} torch threads)\n")
    print("| method | preset | parameters | published | deviation | seconds | × Smits | paper CPU (s) |")
    print("|---|---|---:|---:|---:|---:|---:|---:|")
    for r in rows:
        n, pub, preset = info[r["model"]]
        dev = "–" if not pub or preset != "full" else f"{100 * (n - pub) / pub:+.1f} %"
        paper = PAPER_SECONDS.get(r["model"], (None, None))[0] if not args.quick else None
        print(f"| {r['model']} | {preset} | {n:,} | {'–' if not pub else f'{pub:,}'} | {dev} | "
              f"{r['seconds']:.3f} | {r['seconds'] / ref:.1f} | "
              f"{'–' if paper is None else f'{paper:.3f}'} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
