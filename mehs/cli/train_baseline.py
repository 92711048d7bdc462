"""`mehs train-baseline` — fit the exposure-invariant root-polynomial regression SSR baseline."""

from __future__ import annotations


def configure(parser):
    parser.add_argument("dataset", metavar="DATASET",
                        help="dataset folder (manifest.json) or a plain folder of pairs")
    parser.add_argument("--out", "-o", required=True, metavar="MODEL",
                        help="model file to write (.npz, or .json)")
    parser.add_argument("--split", default="train",
                        help="manifest split to fit on, or 'all' (default: %(default)s; "
                             "a plain folder of pairs uses all its pairs)")
    parser.add_argument("--degree", type=int, choices=[1, 2, 3], default=2,
                        help="root-polynomial degree (default: %(default)s)")
    parser.add_argument("--samples", type=int, default=200_000,
                        help="training pixels sampled over the scenes (default: %(default)s)")
    parser.add_argument("--input", choices=["hdr", "ldr"], default="hdr",
                        help="RGB the baseline learns from (default: %(default)s)")
    parser.add_argument("--ridge", type=float, default=1e-6,
                        help="relative ridge regularisation (default: %(default)s)")
    parser.add_argument("--seed", type=int, default=0,
                        help="seed of the training-pixel sampling (default: %(default)s)")


def run(args):
    from pathlib import Path

    from mehs.ssr.baselines import RegressionModel, check_model_path, fit_regression_baseline
    from mehs.ssr.data import load_pairs

    check_model_path(args.out, RegressionModel.FORMAT)  # before the fit, not after
    root = Path(args.dataset)
    split = None if args.split == "all" or not (root / "manifest.json").is_file() else args.split
    pairs = load_pairs(root, split=split)
    model = fit_regression_baseline(pairs, degree=args.degree, n_samples=args.samples,
                                    input=args.input, ridge=args.ridge, seed=args.seed,
                                    progress=True)
    model.info.update({"dataset": str(root), "split": split})
    out = model.save(args.out)
    print(f"fitted root-polynomial regression (degree {model.degree}) on "
          f"{model.info['n_samples']} pixels of {len(pairs)} scenes "
          f"({split or 'all'}) → {out}")
    return 0
