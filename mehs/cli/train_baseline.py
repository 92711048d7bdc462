"""`mehs train-baseline` — fit the exposure-invariant root-polynomial regression SSR baseline."""

from __future__ import annotations


def configure(parser):
    parser.add_argument("dataset", metavar="DATASET",
                        help="dataset folder (manifest.json), a plain folder of pairs, or a "
                             "public SSR dataset (ARAD-1K, ARAD, ICVL, CAVE, KAUST; see --format)")
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
    parser.add_argument("--preprocess", choices=["off", "on"], default="off",
                        help="fit on Reinhard pre-processed RGB (recorded in the model: the "
                             "evaluation scores it only with that pre-processing) "
                             "(default: %(default)s)")
    parser.add_argument("--target", choices=["auto", "shape", "spectra"], default="auto",
                        help="what the fit predicts: 'shape' (the spectrum over its X+Y+Z, "
                             "always luminance-restored; the paper's spectral similarity) or "
                             "'spectra' (absolute); 'auto': shape with --preprocess on, where "
                             "tone-mapped RGB cannot determine absolute spectra, else spectra "
                             "(default: %(default)s)")
    from mehs.cli.evaluate import add_preprocessing_args

    add_preprocessing_args(parser, "with --preprocess on")
    parser.add_argument("--seed", type=int, default=0,
                        help="seed of the training-pixel sampling (default: %(default)s)")
    from mehs.cli._sources import add_source_arguments

    add_source_arguments(parser)


def run(args):
    from pathlib import Path

    from mehs.ssr.baselines import RegressionModel, check_model_path, fit_regression_baseline
    from mehs.ssr.data import load_pairs

    check_model_path(args.out, RegressionModel.FORMAT)  # before the fit, not after
    from mehs.cli._overwrite import check_writable
    from mehs.io.atomic import refuse_inside_raw_capture

    refuse_inside_raw_capture(args.out)  # a model file beside a raw cube changes the capture
    check_writable(args.out)
    from mehs.cli._sources import apply_source_arguments

    root = Path(args.dataset)
    apply_source_arguments(args, root)
    split = None if args.split == "all" else args.split
    if split is not None and not (root / "manifest.json").is_file():
        from mehs.ssr.data import nonempty_splits

        have = set(nonempty_splits(root))
        if not have:
            split = None  # a plain folder of pairs, or a public set without splits: all scenes
        elif split not in have:
            # falling back to every scene would fit on the scenes the evaluation scores
            # (e.g. a download of ARAD's validation folder alone)
            from mehs.errors import InputError

            raise InputError(f"no {split!r} split in this dataset (has {', '.join(sorted(have))}); "
                             "choose one with --split, or --split all to fit on every scene",
                             root)
    pairs = load_pairs(root, split=split)
    from mehs.cli.evaluate import preprocessing_from_args

    from mehs.cli import progress_bars

    spec = preprocessing_from_args(args) if args.preprocess == "on" else None
    model = fit_regression_baseline(pairs, degree=args.degree, n_samples=args.samples,
                                    input=args.input, ridge=args.ridge, seed=args.seed,
                                    preprocessing=spec, progress=progress_bars(),
                                    target=None if args.target == "auto" else args.target)
    model.info.update({"dataset": str(root), "split": split})
    out = model.save(args.out)
    print(f"fitted root-polynomial regression (degree {model.degree}) on "
          f"{model.info['n_samples']} pixels of {len(pairs)} scenes "
          f"({split or 'all'}, {args.input.upper()}-RGB, "
          f"{spec.label() if spec else 'no pre-processing'}, target {model.target}) → {out}")
    return 0
