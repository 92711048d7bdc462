"""`mehs paper` — train every registered method in both settings and write the paper's Tables 1–5."""

from __future__ import annotations


def configure(parser):
    parser.add_argument("dataset", metavar="DATASET",
                        help="dataset folder with train/val/test splits (trained on train, "
                             "scored on test)")
    parser.add_argument("--out", "-o", required=True, metavar="DIR",
                        help="output folder (runs/, eval_main/, figures/, paper.md, paper.html); "
                             "re-running resumes")
    parser.add_argument("--real", metavar="DATASET2", default=None,
                        help="real HDR-HS dataset for Table 3 and Figure 10 (the paper's ME HS set)")
    parser.add_argument("--quick", action="store_true",
                        help="tiny presets, 3 epochs, few patches: minutes on a CPU")
    parser.add_argument("--preset", default=None,
                        help="architecture preset (default: full, or tiny with --quick)")
    parser.add_argument("--epochs", type=int, default=None,
                        help="epochs per network (default: 100, the paper's; 3 with --quick)")
    parser.add_argument("--device", default="auto",
                        help="training device: auto (CUDA when available; default), cpu, cuda, cuda:N")
    parser.add_argument("--arch", action="append", default=None, metavar="NAME",
                        help="only this registered architecture (repeatable; default: all)")
    parser.add_argument("--baselines", default="smits",
                        help="fixed baselines beside the networks (default: %(default)s)")
    parser.add_argument("--checkpoint", action="append", default=[], metavar="RUN=PATH",
                        help="use this checkpoint for RUN (<arch>-<learning>-pp_<on|off>) "
                             "instead of training it (repeatable)")
    parser.add_argument("--timing-size", default=None, metavar="WxH",
                        help="image size for Table 5 (default: 2048x1024, the paper's; 512x256 "
                             "with --quick, where AWAN's global attention alone would take "
                             "minutes in tiles on a CPU)")
    from mehs.cli.evaluate import add_preprocessing_args

    add_preprocessing_args(parser, "the networks are trained with")
    parser.set_defaults(reinhard_key="none")
    parser.add_argument("--seed", type=int, default=0,
                        help="seed of training, the regression timing baseline and the "
                             "figures' pixel picks (default 0)")
    parser.add_argument("--no-progress", action="store_true", help="no progress bars")


def run(args):
    from mehs.cli import progress_bars
    from mehs.cli.evaluate import preprocessing_from_args
    from mehs.errors import InputError
    from mehs.ssr.paper import run_paper

    from pathlib import Path

    # before the first of 20-odd training runs starts (and creates --out), not inside it
    for what, path in (("dataset", args.dataset), ("--real dataset", args.real)):
        if path is not None and not Path(path).exists():
            raise InputError(f"no such {what}", path)
    if args.timing_size is None:
        args.timing_size = "512x256" if args.quick else "2048x1024"
    try:
        w, h = (int(v) for v in args.timing_size.lower().split("x"))
    except ValueError:
        raise InputError(f"--timing-size must be WxH, got {args.timing_size!r}") from None
    if w < 16 or h < 16:
        raise InputError(f"--timing-size must be at least 16x16, got {args.timing_size!r}")
    if args.epochs is not None and args.epochs < 1:
        raise InputError("--epochs must be at least 1")
    ckpts = {}
    for item in args.checkpoint:
        run_name, sep, path = item.partition("=")
        if not sep or not run_name or not path:
            raise InputError(f"--checkpoint must be RUN=PATH, got {item!r}")
        ckpts[run_name.strip()] = path.strip()
    from mehs.cli._overwrite import check_writable, refuse_foreign_folder

    # re-running resumes a paper folder; a folder holding other files is not one
    refuse_foreign_folder(args.out, PAPER_NAMES, force=None, what="a mehs paper run")
    check_writable(args.out)
    no_networks = _no_networks_note()
    if no_networks:
        import sys

        print(f"mehs paper: {no_networks}", file=sys.stderr)
    md = run_paper(args.dataset, args.out, real=args.real, quick=args.quick, preset=args.preset,
                   epochs=args.epochs, device=args.device,
                   baselines=[b for b in args.baselines.split(",") if b.strip()],
                   checkpoints=ckpts, archs=args.arch,
                   preprocessing=preprocessing_from_args(args), timing_shape=(h, w),
                   seed=args.seed, progress=progress_bars(args.no_progress))
    print(md.read_text(encoding="utf-8"))
    print(f"written: {md} and {md.with_suffix('.html')}")
    if no_networks:
        print(f"note: {no_networks}")
    return 0


#: What ``mehs paper --out DIR`` writes (:mod:`mehs.ssr.paper`).
PAPER_NAMES = ("state.json", "paper.md", "paper.html", "runs", "eval_main", "eval_real",
               "figures")


def _no_networks_note() -> str | None:
    """Why the tables will hold the fixed baselines only, or None when networks are
    registered: without the torch extra no SSR network is (mehs.ssr.registry), and the
    run would otherwise end with empty network rows and no word why."""
    from mehs.ssr.registry import list_architectures

    if list_architectures():
        return None
    import importlib.util

    why = ("PyTorch is not installed" if importlib.util.find_spec("torch") is None
           else "PyTorch is installed but no network module could be loaded")
    return (f"no SSR network to train ({why}): the tables hold the fixed baselines only; "
            'install the torch extra with python -m pip install -e ".[torch]"')
