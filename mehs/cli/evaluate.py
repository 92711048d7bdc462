"""`mehs evaluate` — score SSR models on a dataset or a folder of pairs (paper Tables 2–5)."""

from __future__ import annotations


def configure(parser):
    parser.add_argument("dataset", metavar="DATASET",
                        help="dataset folder (manifest.json), a plain folder of pairs "
                             "(<stem>.hdr with <stem>.exr and/or <stem>.png), or a public SSR "
                             "dataset (ARAD-1K, ARAD, ICVL, CAVE, KAUST, Harvard; see --format)")
    parser.add_argument("--models", "-m", default="smits,mallett",
                        help="comma-separated models, each optionally NAME=SPEC to name its "
                             "row: built-in names (smits, mallett, regression = fitted on the "
                             "train split once per pre-processing setting; see --list-models), "
                             "package.module:function, file.py:function, model.onnx, "
                             "model.npz (from train-baseline), a .pt checkpoint "
                             "(default: %(default)s)")
    parser.add_argument("--preprocess", choices=["off", "on", "both"], default="both",
                        help="Reinhard pre-processing settings to score; each model is scored "
                             "only in the one it was trained for (default: %(default)s)")
    add_preprocessing_args(parser, "for fixed baselines scored with pre-processing and "
                                   "regressions fitted here")
    parser.add_argument("--fixed-preprocess", action="store_true",
                        help="also score fixed baselines (Smits, Mallett) with pre-processing "
                             "(the paper shows '–' there)")
    parser.add_argument("--pixels", action="append", default=[], metavar="SCENE:ROW,COL",
                        help="plot the spectra at this pixel in the report (repeatable)")
    parser.add_argument("--mrae-threshold", type=float, default=0.0, metavar="T",
                        help="MRAE over elements with ground truth > T (default: %(default)s)")
    parser.add_argument("--mrae-relative", action="store_true",
                        help="--mrae-threshold is a fraction of each image's maximum")
    parser.add_argument("--mrae-bands", default=None, metavar="LO-HI",
                        help="MRAE over the bands LO..HI nm only, e.g. 420-680")
    parser.add_argument("--score-unresolved", action="store_true",
                        help="also score pixels and elements whose ground truth is not resolved "
                             "above its own noise (mask bit 8 of a mehs dataset; the MRAE's "
                             "10-sigma floor): the paper's protocol, every measured pixel")
    parser.add_argument("--input", default="hdr",
                        help="RGB input(s): hdr, ldr or hdr,ldr (default: %(default)s)")
    parser.add_argument("--restore", nargs="?", const="on", default="on",
                        choices=["on", "off", "both"],
                        help="luminance restoration (X+Y+Z)_rgb/(X+Y+Z)_S·S (default: on)")
    parser.add_argument("--no-restore", dest="restore", action="store_const", const="off",
                        help="same as --restore off")
    parser.add_argument("--crop", type=int, default=0, metavar="N",
                        help="border pixels removed on every side before scoring (default 0)")
    parser.add_argument("--split", default="auto",
                        help="manifest split to score (train/val/test), 'all', or 'auto' = "
                             "test if the dataset has one, else val (ARAD-1K's official "
                             "validation list, the paper's test set), else all "
                             "(default: %(default)s)")
    parser.add_argument("--out", "-o", default="evaluation", metavar="DIR",
                        help="results folder (evaluation.json, results.csv, tables.md, "
                             "figures/) (default: %(default)s)")
    parser.add_argument("--figures", default="all", metavar="N|all",
                        help="scenes kept for the report's figures: best-method and SAM maps, "
                             "spectra (default: %(default)s)")
    parser.add_argument("--timing", action="store_true",
                        help="also time each model on a 2048×1024 image (paper Table 5)")
    parser.add_argument("--timing-size", default="2048x1024", metavar="WxH",
                        help="image size for --timing (default: %(default)s)")
    parser.add_argument("--report", action="store_true",
                        help="also write DIR/report.html")
    parser.add_argument("--markdown", action="store_true",
                        help="print the Markdown tables instead of plain text")
    parser.add_argument("--seed", type=int, default=0,
                        help="seed of the regression baseline's pixel sampling and of the "
                             "figures' pixel picks (default: %(default)s)")
    parser.add_argument("--force", action="store_true",
                        help="replace the results of an earlier evaluation in --out "
                             "(refused without it)")
    parser.add_argument("--verify", action="store_true",
                        help="hash every dataset file against manifest.json before scoring "
                             "(default: only files whose size or mtime changed)")
    from mehs.cli._sources import add_source_arguments

    add_source_arguments(parser)
    parser.add_argument("--list-models", action="store_true",
                        help="list the registered model names and exit")


def add_preprocessing_args(parser, what: str) -> None:
    """``--reinhard-key`` / ``--reinhard-scale`` (shared with train-baseline)."""
    parser.add_argument("--reinhard-key", default="0.18", metavar="KEY|none",
                        help=f"Reinhard pre-processing {what}: each image scaled so its "
                             "log-average luminance is KEY, then x/(1+x); 'none' = a fixed "
                             "--reinhard-scale (default: %(default)s)")
    parser.add_argument("--reinhard-scale", type=float, default=1.0, metavar="S",
                        help="fixed scale with --reinhard-key none: x·S/(1+x·S); S=1 is the "
                             "paper's x/(1+x) on the data as given (default: %(default)s)")


def preprocessing_from_args(args):
    """The :class:`~mehs.ssr.preprocess.Preprocessing` the options describe."""
    from mehs.errors import InputError
    from mehs.ssr.preprocess import Preprocessing

    key = None if str(args.reinhard_key).lower() == "none" else args.reinhard_key
    try:
        return Preprocessing(key=None if key is None else float(key), scale=args.reinhard_scale)
    except ValueError as exc:
        raise InputError(f"--reinhard-key/--reinhard-scale: {exc}") from None


def _figures(text: str) -> int:
    from mehs.errors import InputError

    if str(text).lower() == "all":
        return -1
    try:
        n = int(text)
    except ValueError:
        n = -2
    if n < 0:
        raise InputError(f"--figures must be a count ≥ 0 or 'all', got {text!r}")
    return n


def _bands(text):
    from mehs.errors import InputError

    if text is None:
        return None
    try:
        lo, hi = (float(v) for v in str(text).replace(",", "-").split("-"))
    except ValueError:
        lo = hi = float("nan")
    if not (lo <= hi):
        raise InputError(f"--mrae-bands must be LO-HI in nm with LO ≤ HI, got {text!r}")
    return lo, hi


#: What ``mehs evaluate --out DIR`` writes (:mod:`mehs.ssr.results_io`, the report).
RESULT_NAMES = ("evaluation.json", "results.csv", "summary.csv", "tables.md", "tables.txt",
                "figures", "report.html", "report_files")


def _all_scenes_note(asked: str, scored: str | None, dataset, n_scenes) -> str | None:
    """A note when ``--split auto`` found neither a test nor a val split and scored every
    scene, the train split's included: a model fitted on them scores optimistically there,
    and nothing else in the output says which scenes were scored."""
    if asked != "auto" or scored is not None:
        return None
    import json
    from pathlib import Path

    try:
        splits = json.loads((Path(dataset) / "manifest.json").read_text(encoding="utf-8"))["splits"]
        n_train = len(splits.get("train") or [])
    except (OSError, ValueError, KeyError, TypeError, AttributeError):
        return None  # a plain folder of pairs or a public set: no splits to speak of
    if not n_train:
        return None
    return (f"the dataset has no test or val split, so every scene was scored ({n_scenes}), "
            f"the {n_train} of its train split included: a model fitted on them scores "
            "optimistically there; build the dataset with a test split to score held-out "
            "scenes")


def run(args):
    from mehs.errors import InputError
    from mehs.ssr.evaluate import evaluate
    from mehs.ssr.metrics import METRIC_NAMES

    if args.list_models:
        from mehs.ssr.models import list_models

        for name, desc in list_models().items():
            print(f"{name:12s} {desc}")
        return 0
    try:
        w, h = (int(v) for v in args.timing_size.lower().split("x"))
    except ValueError:
        raise InputError(f"--timing-size must be WxH, got {args.timing_size!r}") from None
    if w < 1 or h < 1:
        raise InputError(f"--timing-size must be at least 1x1 pixels, got {args.timing_size!r}")
    from mehs.cli._sources import apply_source_arguments

    apply_source_arguments(args, args.dataset)
    from pathlib import Path

    from mehs.cli._overwrite import check_writable, refuse_existing, refuse_foreign_folder

    refuse_foreign_folder(args.out, RESULT_NAMES, force=args.force, what="mehs evaluate's results")
    refuse_existing([Path(args.out) / "evaluation.json"], args.force)
    check_writable(args.out)
    if args.verify:
        from mehs.ssr.data import load_pairs

        load_pairs(args.dataset, verify="full")
    inputs = tuple(s.strip() for s in args.input.split(",") if s.strip())
    split = None if args.split == "all" else args.split
    from mehs.cli import progress_bars

    res = evaluate(args.dataset, args.models, preprocess=args.preprocess, inputs=inputs,
                   restore={"on": True, "off": False, "both": "both"}[args.restore],
                   crop=args.crop, split=split, out=args.out, figures=_figures(args.figures),
                   timing=args.timing, timing_shape=(h, w), seed=args.seed,
                   progress=progress_bars(),
                   preprocessing=preprocessing_from_args(args),
                   fixed_preprocess=args.fixed_preprocess, pixels=args.pixels,
                   mrae_threshold=args.mrae_threshold, mrae_relative=args.mrae_relative,
                   mrae_bands=_bands(args.mrae_bands), score_unresolved=args.score_unresolved)
    fmt = "markdown" if args.markdown else "text"
    print(res.tables(fmt))
    if any(s.get(f"{k}_undefined") for s in res.summary for k in METRIC_NAMES):
        print("note: some images had no usable pixels for a metric (see summary.csv)")
    unresolved = max((s.get("unresolved_pixels") or 0 for s in res.summary), default=0)
    floor = max((s.get("mrae_floor_excluded") or 0 for s in res.summary), default=0)
    if unresolved or floor:
        print(f"note: {unresolved} pixels whose ground truth is not resolved above its noise "
              f"were not scored, and {floor} more elements were left out of MRAE "
              f"(--score-unresolved scores them)")
    for note in res.config.get("notes", []):
        print(f"note: {note}")
    fallback = _all_scenes_note(args.split, res.config.get("split"), args.dataset,
                                res.config.get("n_scenes"))
    if fallback:
        print(f"note: {fallback}")
    for s in res.skipped:
        print(f"skipped {s['scene']} ({s['input']}): {s['reason']}")
    print(f"results: {res.out}")
    if args.report:
        from mehs.ssr.report import write_evaluation_report

        print(f"report: {write_evaluation_report(res.out)}")
    return 0
