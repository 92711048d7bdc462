"""`mehs evaluate` — score SSR models on a dataset or a folder of pairs (paper Tables 2–5)."""

from __future__ import annotations


def configure(parser):
    parser.add_argument("dataset", metavar="DATASET",
                        help="dataset folder (manifest.json) or a plain folder of pairs "
                             "(<stem>.hdr with <stem>.exr and/or <stem>.png)")
    parser.add_argument("--models", "-m", default="smits,mallett",
                        help="comma-separated models: built-in names (smits, mallett, "
                             "regression = fitted on the train split; see --list-models), "
                             "package.module:function, file.py:function, model.onnx, "
                             "model.npz (from train-baseline) (default: %(default)s)")
    parser.add_argument("--preprocess", choices=["off", "on", "both"], default="both",
                        help="Reinhard x/(1+x) on the input (default: %(default)s)")
    parser.add_argument("--input", default="hdr",
                        help="RGB input(s): hdr, ldr or hdr,ldr (default: %(default)s)")
    parser.add_argument("--restore", nargs="?", const="on", default="on",
                        choices=["on", "off", "both"],
                        help="luminance restoration (X+Y+Z)_rgb/(X+Y+Z)_S·S (default: on)")
    parser.add_argument("--no-restore", dest="restore", action="store_const", const="off",
                        help="same as --restore off")
    parser.add_argument("--crop", type=int, default=0, metavar="N",
                        help="border pixels removed on every side before scoring")
    parser.add_argument("--split", default="auto",
                        help="manifest split to score (train/val/test), 'all', or 'auto' = "
                             "test if the manifest has one (default: %(default)s)")
    parser.add_argument("--out", "-o", default="evaluation", metavar="DIR",
                        help="results folder (evaluation.json, results.csv, tables.md, "
                             "figures/) (default: %(default)s)")
    parser.add_argument("--figures", type=int, default=2, metavar="N",
                        help="scenes kept for the report's figures (default: %(default)s)")
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
    parser.add_argument("--list-models", action="store_true",
                        help="list the registered model names and exit")


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
    from pathlib import Path

    from mehs.cli._overwrite import refuse_existing

    refuse_existing([Path(args.out) / "evaluation.json"], args.force)
    if args.verify:
        from mehs.ssr.data import load_pairs

        load_pairs(args.dataset, verify="full")
    inputs = tuple(s.strip() for s in args.input.split(",") if s.strip())
    split = None if args.split == "all" else args.split
    res = evaluate(args.dataset, args.models, preprocess=args.preprocess, inputs=inputs,
                   restore={"on": True, "off": False, "both": "both"}[args.restore],
                   crop=args.crop, split=split, out=args.out, figures=args.figures,
                   timing=args.timing, timing_shape=(h, w), seed=args.seed, progress=True)
    fmt = "markdown" if args.markdown else "text"
    print(res.tables(fmt))
    if any(s.get(f"{k}_undefined") for s in res.summary for k in METRIC_NAMES):
        print("note: some images had no usable pixels for a metric (see summary.csv)")
    for note in res.config.get("notes", []):
        print(f"note: {note}")
    for s in res.skipped:
        print(f"skipped {s['scene']} ({s['input']}): {s['reason']}")
    print(f"results: {res.out}")
    if args.report:
        from mehs.ssr.report import write_evaluation_report

        print(f"report: {write_evaluation_report(res.out)}")
    return 0
