"""`mehs train-ssr` — train a network of the SSR zoo (``--arch``) on a dataset.

Every architecture (the paper's ``hdrssr``, ``mikamoto``, ``galliani``, ``hscnnd``,
``awan``, ``mstpp``) trains with the same recipe in either learning mode
(``--mode similarity|e2e``), at the published size (``--preset full``) or one that
trains on two CPU cores (``--preset small``). The checkpoint records the
architecture, preset, learning mode and trained input (HDR/LDR, Reinhard on/off and
its scale).

Needs the torch extra (``pip install "mehs[torch]"``). Reads a dataset folder
(format 3), a plain folder of pairs or a public SSR dataset; trains on the ``train``
split (all scenes when the dataset defines no split; an error when it defines splits
but no training scenes), validates on ``val`` when the dataset also has a test split,
and otherwise — ARAD-1K, whose official validation list is what gets scored, the
paper's test set — on ``--val-count`` scenes (10, as the paper) held out of the train
split by ``--seed``. The scene ids trained and validated on are recorded in the
checkpoints (``extra``). Writes checkpoints to ``--out`` and, unless ``--no-onnx``,
``OUT/model.onnx`` exported from the best checkpoint.
"""

from __future__ import annotations

import sys

from mehs.errors import InputError

#: Zoo names, for the help text only (the zoo itself needs torch to import).
ARCH_HELP = "hdrssr (the paper's), mikamoto, galliani, hscnnd, awan, mstpp"


def configure(parser):
    parser.add_argument("dataset", help="dataset folder (manifest.json), a plain folder of pairs, or a "
                             "public SSR dataset (ARAD-1K, ARAD, ICVL, CAVE, KAUST; see --format)")
    parser.add_argument("--out", required=True, help="output folder for checkpoints and model.onnx")
    parser.add_argument("--arch", default="hdrssr",
                        help=f"architecture: {ARCH_HELP} (default hdrssr; "
                             "`python -m mehs.ssr.net` lists them with parameter counts)")
    parser.add_argument("--preset", choices=("full", "small", "tiny"), default="small",
                        help="full: the published size (a GPU job); small: trains on two CPU "
                             "cores (default); tiny: tests")
    parser.add_argument("--mode", choices=("similarity", "e2e"), default="similarity",
                        help="similarity: learn the standard spectrum HS/(X+Y+Z), luminance "
                             "restored afterwards (default, the paper's ◇); e2e: MSE on the "
                             "spectra, nothing restored")
    parser.add_argument("--param", action="append", default=[], metavar="KEY=VALUE",
                        help="override one architecture parameter of the preset, e.g. "
                             "growth=4, n_blocks=10, down_layers=2,2 (repeatable)")
    parser.add_argument("--epochs", type=int, default=40, help="total epochs (default 40)")
    parser.add_argument("--batch", type=int, default=8, help="patches per batch (default 8)")
    parser.add_argument("--patch", type=int, default=64, help="patch side in pixels (default 64)")
    parser.add_argument("--patches-per-image", type=int, default=16,
                        help="random patches drawn per training image per epoch (default 16)")
    parser.add_argument("--device", default="cpu", help="torch device: cpu (default), cuda, cuda:1, mps")
    parser.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    parser.add_argument("--val-count", type=int, default=10,
                        help="when the dataset has no test split (ARAD-1K: its validation list "
                             "is what gets scored, as the paper's test set), validate on this "
                             "many scenes held out of the train split instead, as the paper "
                             "did (default 10; 0: no validation)")
    parser.add_argument("--resume", action="store_true",
                        help="continue the run in --out from its last.pt")
    parser.add_argument("--no-reinhard", dest="reinhard", action="store_false",
                        help="feed linear RGB to the network instead of Reinhard x/(1+x)")
    parser.add_argument("--reinhard-scale", type=float, default=1.0,
                        help="Reinhard scale s: the network sees (x/s)/(1+x/s) (default 1, "
                             "the data's unit); recorded in the checkpoint")
    parser.add_argument("--input", choices=("hdr", "ldr"), default="hdr",
                        help="train on pseudo-HDR-RGB (default) or on linearised LDR-RGB")
    parser.add_argument("--lr-max", type=float, default=None,
                        help="η_max (default 0.002; AWAN 0.0002 as in the paper)")
    parser.add_argument("--lr-min", type=float, default=None,
                        help="η_min (default 0.0001; AWAN 0.00001 as in the paper)")
    parser.add_argument("--loss", choices=("mse", "mrae"), default="mse",
                        help="training loss: mse (default; the paper's end-to-end loss) or "
                             "mrae (NTIRE / MST++'s); recorded in the checkpoint")
    parser.add_argument("--t0", type=int, default=20, help="warm-restart period T0 in epochs (default 20)")
    parser.add_argument("--no-onnx", dest="onnx", action="store_false",
                        help="do not export OUT/model.onnx at the end")
    parser.add_argument("--threads", type=int, default=0,
                        help="torch CPU threads (default 0: torch's choice); 1 is often "
                             "faster on a busy machine")
    parser.add_argument("--quiet", action="store_true", help="no progress bar")
    from mehs.cli._sources import add_source_arguments

    add_source_arguments(parser)


def parse_params(items) -> dict:
    """``["growth=4", "down_layers=2,2", "dropout=0.1", "attention=false"]`` → typed dict."""
    out = {}
    for item in items:
        key, sep, raw = str(item).partition("=")
        key = key.strip().replace("-", "_")
        if not sep or not key or not raw.strip():
            raise InputError(f"--param must be KEY=VALUE, got {item!r}")
        vals = [_parse_value(v.strip(), item) for v in raw.split(",")]
        out[key] = vals[0] if "," not in raw else tuple(vals)
    return out


def _parse_value(v: str, item: str):
    if v.lower() in ("true", "false"):
        return v.lower() == "true"
    for cast in (int, float):
        try:
            return cast(v)
        except ValueError:
            pass
    raise InputError(f"--param {item!r}: {v!r} is not a number or true/false")


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


def _splits(dataset, sp: dict | None = None):
    """``(train split or None, val split or None)`` of ``dataset`` (``sp``: its
    :func:`mehs.ssr.data.nonempty_splits`, if listed already); ``None`` for training means every
    scene, allowed only when the dataset defines no split at all."""
    from mehs.ssr.data import nonempty_splits

    sp = nonempty_splits(dataset) if sp is None else sp
    if sp and "train" not in sp:
        # training on "all scenes" here would train on the very scenes the evaluation
        # scores (an evaluation-only set such as ME HS, or a download of ARAD's
        # validation folder alone) and validate on scenes it trained on
        raise InputError(f"the dataset defines splits ({', '.join(sorted(sp))}) but no "
                         "training scenes; train on a dataset with a train split", dataset)
    return ("train" if "train" in sp else None), ("val" if "val" in sp else None)


def hold_out_validation(pairs, count: int, seed: int):
    """Split training pairs into ``(train, validation)``: ``min(count, len − 1)`` scenes
    drawn reproducibly from ``seed`` (:func:`mehs.dataset.splits.pick_holdout`)."""
    from mehs.dataset.splits import pick_holdout

    n = max(0, min(int(count), len(pairs) - 1))
    held = set(pick_holdout([p.id for p in pairs], n, seed))
    return [p for p in pairs if p.id not in held], [p for p in pairs if p.id in held]


def run(args):
    try:
        import torch  # noqa: F401
    except ImportError:
        raise InputError("'mehs train-ssr' needs PyTorch: pip install \"mehs[torch]\"") from None
    import math
    from pathlib import Path

    from mehs.ssr.net.base import NetConfig
    from mehs.ssr.net.export import export_onnx
    from mehs.ssr.net.train import TrainConfig, history_summary, train_network
    from mehs.ssr.net.zoo import get_architecture

    for name in ("epochs", "batch", "patch", "patches_per_image", "t0"):
        if getattr(args, name) < 1:
            raise InputError(f"--{name.replace('_', '-')} must be at least 1")
    if args.threads < 0:
        raise InputError("--threads must be 0 (torch's choice) or more")
    if not (math.isfinite(args.reinhard_scale) and args.reinhard_scale > 0):
        raise InputError(f"--reinhard-scale must be a positive number, got {args.reinhard_scale}")
    arch = get_architecture(args.arch)
    params = parse_params(args.param)
    arch.params(args.preset, params)  # refuse a bad --param before reading the data
    if args.threads:
        torch.set_num_threads(args.threads)
    from mehs.cli._sources import apply_source_arguments

    apply_source_arguments(args, args.dataset)
    if args.val_count < 0:
        raise InputError("--val-count must be 0 or more")
    from mehs.ssr.data import nonempty_splits

    sp = nonempty_splits(args.dataset)
    train_split, val_split = _splits(args.dataset, sp)
    pairs, wl = load_training_pairs(args.dataset, split=train_split, kind=args.input)
    val_source = val_split
    if val_split and "test" not in sp:
        # No test split: the val split is the one scored (ARAD-1K's official validation
        # list, which the paper used as its test set, §3.6.1). Choosing best.pt on it would
        # select the model on its own test scenes, so validate as the paper did: on scenes
        # drawn from the training data, which are then not trained on.
        pairs, val = hold_out_validation(pairs, args.val_count, args.seed)
        val_source = f"{len(val)} held out of {train_split or 'all scenes'} (seed {args.seed})"
    elif val_split:
        val = load_training_pairs(args.dataset, split=val_split, kind=args.input)[0]
    else:
        val = []
    net_config = NetConfig(arch=args.arch, preset=args.preset, mode=args.mode,
                           wavelengths=wl.tolist(), reinhard=args.reinhard,
                           reinhard_scale=args.reinhard_scale, input=args.input, params=params)
    lr = {k: v for k, v in (("lr_max", args.lr_max), ("lr_min", args.lr_min)) if v is not None}
    tc = TrainConfig.for_arch(args.arch, epochs=args.epochs, batch=args.batch, patch=args.patch,
                              patches_per_image=args.patches_per_image, T0=args.t0,
                              seed=args.seed, device=args.device, loss=args.loss, **lr)
    lr_max, lr_min = tc.lr_max, tc.lr_min
    print(f"training {args.arch} ({args.preset}, {args.mode}) on {len(pairs)} scene(s)"
          f"{f', validating on {len(val)}' if val else ''} ({args.input.upper()}-RGB, "
          f"{'Reinhard' if args.reinhard else 'linear'} input), {args.epochs} epochs, "
          f"lr {lr_max:g}..{lr_min:g}, device {args.device}")
    from mehs.cli import progress_bars

    res = train_network(pairs, args.out, net_config=net_config, train_config=tc, val_pairs=val,
                        resume=args.resume, progress=progress_bars(args.quiet),
                        extra={"dataset": str(Path(args.dataset).resolve()),
                               "input": args.input, "train_split": train_split,
                               "val_split": val_source,
                               "train_ids": [p.id for p in pairs],
                               "val_ids": [p.id for p in val]})
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
