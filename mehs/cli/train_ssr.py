"""`mehs train-ssr` — train the HDR SSR network (or the plain FC-DenseNet) on a dataset.

Needs the torch extra (``pip install "mehs[torch]"``). Reads a dataset folder
(format 3) or a plain folder of pairs; trains on the ``train`` split (all
scenes when there is no split), validates on ``val`` when it has scenes, writes
checkpoints to ``--out`` and, unless ``--no-onnx``, ``OUT/model.onnx`` exported
from the best checkpoint.
"""

from __future__ import annotations

import sys

from mehs.errors import InputError

NET_SIZES = {
    # ~80 k parameters: trains on a laptop CPU in minutes
    "small": dict(first_channels=16, down_layers=(2, 2, 2), bottleneck_layers=2, growth=8),
    "tiny": dict(first_channels=8, down_layers=(1, 1), bottleneck_layers=1, growth=8),
    # FC-DenseNet-56/67-sized (Jégou et al. 2017 use growth 12-16, 4-5 levels): a GPU job
    "large": dict(first_channels=48, down_layers=(4, 5, 7, 10), bottleneck_layers=12,
                  growth=16),
}


def configure(parser):
    parser.add_argument("dataset", help="dataset folder (manifest.json) or a plain folder of pairs")
    parser.add_argument("--out", required=True, help="output folder for checkpoints and model.onnx")
    parser.add_argument("--variant", choices=("hdrssr", "fcdensenet"), default="hdrssr",
                        help="hdrssr: basis branches, learns spectral similarity (default); "
                             "fcdensenet: plain end-to-end FC-DenseNet, MSE on spectra")
    parser.add_argument("--epochs", type=int, default=40, help="total epochs (default 40)")
    parser.add_argument("--batch", type=int, default=8, help="patches per batch (default 8)")
    parser.add_argument("--patch", type=int, default=64, help="patch side in pixels (default 64)")
    parser.add_argument("--patches-per-image", type=int, default=16,
                        help="random patches drawn per training image per epoch (default 16)")
    parser.add_argument("--device", default="cpu", help="torch device: cpu (default), cuda, cuda:1, mps")
    parser.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    parser.add_argument("--resume", action="store_true",
                        help="continue the run in --out from its last.pt")
    parser.add_argument("--no-reinhard", dest="reinhard", action="store_false",
                        help="feed linear RGB to the network instead of Reinhard x/(1+x)")
    parser.add_argument("--input", choices=("hdr", "ldr"), default="hdr",
                        help="train on pseudo-HDR-RGB (default) or on linearised LDR-RGB")
    parser.add_argument("--size", choices=sorted(NET_SIZES), default="small",
                        help="network size preset (default small)")
    parser.add_argument("--growth", type=int, help="override the preset's growth rate")
    parser.add_argument("--n-basis", type=int, default=10,
                        help="basis functions per branch (default 10)")
    parser.add_argument("--lr-max", type=float, default=0.002, help="η_max (default 0.002)")
    parser.add_argument("--lr-min", type=float, default=0.0001, help="η_min (default 0.0001)")
    parser.add_argument("--t0", type=int, default=20, help="warm-restart period T0 in epochs (default 20)")
    parser.add_argument("--no-onnx", dest="onnx", action="store_false",
                        help="do not export OUT/model.onnx at the end")
    parser.add_argument("--threads", type=int, default=0,
                        help="torch CPU threads (default 0: torch's choice); 1 is often "
                             "faster on a busy machine")
    parser.add_argument("--quiet", action="store_true", help="no progress bar")


def load_training_pairs(dataset, *, split: str | None, kind: str = "hdr"):
    """``mehs.ssr.data`` pairs of ``dataset`` (one split) → list of ``TrainingPair``, wavelengths."""
    import numpy as np

    from mehs.ssr.data import load_pairs
    from mehs.ssr.net.train import TrainingPair

    pairs = load_pairs(dataset, split=split)
    out, wl = [], None
    for p in pairs:
        hs, w = p.hs_array()
        if wl is None:
            wl = np.asarray(w, dtype=np.float64)
        elif w.shape != wl.shape or not np.allclose(w, wl, atol=0.01):
            raise InputError(f"scene {p.id!r} has other bands than the first scene", p.hs_path)
        if not p.has(kind):
            raise InputError(f"scene {p.id!r} has no {kind.upper()}-RGB image", p.hs_path.parent)
        rgb = p.rgb(kind)
        if rgb.shape[:2] != hs.shape[:2]:
            raise InputError(f"scene {p.id!r}: RGB {rgb.shape[:2]} and HS {hs.shape[:2]} differ "
                             "in size", p.hs_path.parent)
        out.append(TrainingPair(rgb, hs, p.valid(hs.shape[:2]), id=p.id))
    return out, wl


def _splits(dataset):
    from mehs.ssr.data import load_pairs

    ps = load_pairs(dataset)
    sp = {k: v for k, v in (ps.splits or {}).items() if v}
    return ("train" if "train" in sp else None), ("val" if "val" in sp else None)


def run(args):
    try:
        import torch  # noqa: F401
    except ImportError:
        raise InputError("'mehs train-ssr' needs PyTorch: pip install \"mehs[torch]\"") from None
    from pathlib import Path

    from mehs.ssr.net.export import export_onnx
    from mehs.ssr.net.model import NetConfig
    from mehs.ssr.net.train import TrainConfig, history_summary, train_network

    for name in ("epochs", "batch", "patch", "patches_per_image", "n_basis", "t0"):
        if getattr(args, name) < 1:
            raise InputError(f"--{name.replace('_', '-')} must be at least 1")
    if args.threads < 0:
        raise InputError("--threads must be 0 (torch's choice) or more")
    if args.threads:
        torch.set_num_threads(args.threads)
    train_split, val_split = _splits(args.dataset)
    pairs, wl = load_training_pairs(args.dataset, split=train_split, kind=args.input)
    val = load_training_pairs(args.dataset, split=val_split, kind=args.input)[0] if val_split else []
    size = dict(NET_SIZES[args.size])
    if args.growth is not None:  # "--growth 0" must be refused, not ignored
        size["growth"] = args.growth
    net_config = NetConfig(variant=args.variant, wavelengths=wl.tolist(), n_basis=args.n_basis,
                           reinhard=args.reinhard, **size)
    tc = TrainConfig(epochs=args.epochs, batch=args.batch, patch=args.patch,
                     patches_per_image=args.patches_per_image, lr_max=args.lr_max,
                     lr_min=args.lr_min, T0=args.t0, seed=args.seed, device=args.device)
    print(f"training {args.variant} on {len(pairs)} scene(s)"
          f"{f', validating on {len(val)}' if val else ''} ({args.input.upper()}-RGB, "
          f"{'Reinhard' if args.reinhard else 'linear'} input), {args.epochs} epochs, "
          f"device {args.device}")
    res = train_network(pairs, args.out, net_config=net_config, train_config=tc, val_pairs=val,
                        resume=args.resume, progress=not args.quiet,
                        extra={"dataset": str(Path(args.dataset).resolve()),
                               "input": args.input, "train_split": train_split,
                               "val_split": val_split})
    print(history_summary(res.history))
    best = res.best_checkpoint or res.last_checkpoint
    print(f"checkpoints: {res.last_checkpoint} (last), {best} (best)")
    if best is not None:
        print(f"evaluate: mehs evaluate {args.dataset} --models smits,mallett,{best}")
    if args.onnx and best is not None:
        from mehs.errors import MehsError

        try:
            onnx_path = export_onnx(best, Path(args.out) / "model.onnx")
        except MehsError as exc:
            # training succeeded and its checkpoints are kept: say what was skipped and how
            # to get it, instead of ending a long run with an exporter traceback
            print(f"note: ONNX export skipped: {exc.problem}. The checkpoints above are "
                  f"complete; export later with: python -c \"from mehs.ssr.net.export import "
                  f"export_onnx; export_onnx('{best}', '{Path(args.out) / 'model.onnx'}')\"",
                  file=sys.stderr)
            return 0
        # the graph applies its own Reinhard step: the evaluation must not add another
        print(f"ONNX model: {onnx_path} (self-contained: linear RGB in; score it with "
              f"--preprocess off)")
    return 0
