"""`mehs build` — build the ME HS dataset from bracketed scenes (or HS cubes with --from-hs)."""

from __future__ import annotations


def configure(parser):
    parser.epilog = ("Exit status: 0 when every scene was built (some may fail the quality "
                     "rules), 1 when a scene could not be built, 2 on bad arguments.")
    parser.add_argument("scenes", nargs="+", metavar="SCENES",
                        help="scene folders (scene.json + exposures/), folders of them, or "
                             "CSV/TOML scene lists (columns scene_id,folder_short,folder_mid,"
                             "folder_long: Specim IQ folders); with --from-hs: ENVI .hdr "
                             "cubes or folders of them")
    parser.add_argument("--out", "-o", required=True, metavar="DATASET",
                        help="dataset folder (created; an existing one is resumed/extended)")
    parser.add_argument("--from-hs", action="store_true",
                        help="inputs are existing HS cubes (31 or 204 bands, ...): resample "
                             "to 31 bands and pair them with RGB, no bracket")
    parser.add_argument("--workers", "-j", type=int, default=None, metavar="N",
                        help="scenes built at once (default: CPU count)")
    parser.add_argument("--scheduler", metavar="ADDRESS", default=None,
                        help="run scenes on a Dask distributed scheduler (needs mehs[dask]); "
                             "the dataset folder must be reachable at the same path")
    parser.add_argument("--force", action="store_true",
                        help="rebuild scenes even when inputs and parameters are unchanged")
    parser.add_argument("--response", metavar="CURVE",
                        help="response curve file to use for every scene instead of "
                             "recovering one per scene")
    parser.add_argument("--calibration", metavar="CAL",
                        help="radiometric calibration file (mehs calibrate): cubes in radiance "
                             "(W sr-1 m-2 nm-1 or relative) instead of DN/ms")
    parser.add_argument("--method", default="poisson",
                        choices=["poisson", "inverse-variance", "robertson", "debevec"],
                        help="merge estimator (default: poisson)")
    parser.add_argument("--ghosts", default="detect", choices=["detect", "deghost", "off"],
                        help="ghost handling (default: detect)")
    parser.add_argument("--ghost-bins", default="auto", metavar="N",
                        help="adjacent bands summed per term of the ghost test's χ² statistic "
                             "(as mehs fuse --ghost-bins; default auto)")
    parser.add_argument("--resample", default="gaussian", choices=["gaussian", "linear", "box"],
                        help="resampling to 400..700 nm step 10 (default: gaussian)")
    parser.add_argument("--fwhm", type=float, default=10.0, help="target FWHM nm (default 10)")
    parser.add_argument("--seed", type=int, default=0,
                        help="seed of sampling and splits (default 0)")
    parser.add_argument("--splits", default="0.7,0.15,0.15", metavar="TRAIN,VAL,TEST",
                        help="split fractions over passing scenes (default 0.7,0.15,0.15)")
    q = parser.add_argument_group("pass/fail rules")
    q.add_argument("--max-ghost", type=float, default=0.01, metavar="F",
                   help="max ghost fraction (default 0.01)")
    q.add_argument("--max-saturated", type=float, default=0.005, metavar="F",
                   help="max saturated-in-every-exposure fraction (default 0.005)")
    q.add_argument("--max-invalid", type=float, default=0.05, metavar="F",
                   help="max other-invalid fraction (default 0.05)")
    q.add_argument("--max-unresolved", type=float, default=None, metavar="F",
                   help="max fraction of pixels whose ground truth is not resolved above its "
                        "noise (mask bit 8; they are never scored). Default: no limit")
    q.add_argument("--min-dr", type=float, default=None, metavar="STOPS",
                   help="min dynamic range in stops (default 4; off with --from-hs)")
    q.add_argument("--max-response-uncertainty", type=float, default=0.02, metavar="F",
                   help="max median relative radiance uncertainty of a recovered response "
                        "curve (default 0.02; see mehs fuse's response check)")
    q.add_argument("--require-calibration", action="store_true",
                   help="fail scenes that are not radiometrically calibrated")
    parser.add_argument("--verify", action="store_true",
                        help="hash every output of a scene before reusing it (default: only "
                             "outputs whose size or mtime changed; damaged scenes are rebuilt)")
    parser.add_argument("--allow-partial", action="store_true",
                        help="fuse scenes whose capture did not finish from their complete "
                             "exposures (refused by default; 'mehs capture --resume' finishes "
                             "them)")
    parser.add_argument("--quiet", "-q", action="store_true", help="no progress bar")


def run(args):
    from mehs.cli import progress_bars
    from mehs.dataset.build import build_dataset, build_from_hs
    from mehs.dataset.quality import QualityRules
    from mehs.errors import InputError

    if args.workers is not None and args.workers < 1:
        raise InputError("--workers must be at least 1")
    from mehs.synthesis.merge_types import consistency_bins_value

    # checked for --from-hs too, whose cubes have no bracket to use it
    args.ghost_bins = consistency_bins_value(args.ghost_bins, what="--ghost-bins")
    from mehs.cli._overwrite import check_writable, refuse_foreign_folder

    # an existing dataset is resumed or extended; any other folder with files is not one
    refuse_foreign_folder(args.out, DATASET_NAMES, force=args.force, what="a mehs dataset")
    check_writable(args.out)
    min_dr = args.min_dr if args.min_dr is not None else (0.0 if args.from_hs else 4.0)
    rules = QualityRules(max_ghost_fraction=args.max_ghost,
                         max_saturated_fraction=args.max_saturated,
                         max_invalid_fraction=args.max_invalid,
                         min_dynamic_range_stops=min_dr,
                         max_response_uncertainty=args.max_response_uncertainty,
                         require_calibration=args.require_calibration,
                         max_noise_floor_fraction=args.max_unresolved)
    common = dict(workers=args.workers, force=args.force, seed=args.seed, splits=args.splits,
                  rules=rules, resample=args.resample, fwhm=args.fwhm,
                  scheduler=args.scheduler, progress=progress_bars(args.quiet), verify=args.verify)
    try:
        if args.from_hs:
            manifest = build_from_hs(args.scenes, args.out, **common)
        else:
            manifest = build_dataset(args.scenes, args.out, response=args.response,
                                     method=args.method, ghosts=args.ghosts,
                                     ghost_bins=args.ghost_bins,
                                     calibration=args.calibration,
                                     allow_partial=args.allow_partial, **common)
    except KeyboardInterrupt:
        _say_interrupted(args.out)
        raise
    scenes = manifest["scenes"]
    n_pass = sum(s["status"] == "pass" for s in scenes)
    print(f"{args.out}: {len(scenes)} scenes, {n_pass} pass, {len(scenes) - n_pass} fail; "
          f"splits " + ", ".join(f"{k} {len(v)}" for k, v in manifest["splits"].items()))
    unit = manifest.get("radiance_unit")
    if unit and unit.startswith("DN"):
        print(f"  radiance unit: {unit} — not radiometrically calibrated (see mehs calibrate)")
    elif unit:
        print(f"  radiance unit: {unit}")
    for s in scenes:
        if s["status"] != "pass":
            print(f"  {s['id']}: fail: {'; '.join(s['reasons'])}")
    # scenes failing a quality rule are a normal outcome; scenes that could not be built are not
    return 1 if any("error" in s for s in scenes) else 0


#: What a dataset folder holds (:mod:`mehs.dataset.build`, :mod:`mehs.dataset.report`).
DATASET_NAMES = ("manifest.json", "index.csv", "scenes", "splits", "report.html",
                 "report_files")


def _say_interrupted(out) -> None:
    """After Ctrl-C: which scenes the dataset holds now, and how to finish it.

    The manifest lists only committed scenes (half-built ones stay in hidden
    ``scenes/.tmp-*`` folders, removed by the next run), so an interrupted dataset looks
    like a smaller complete one; say so, and that the same command finishes it.
    """
    import json
    import sys
    from pathlib import Path

    try:
        doc = json.loads((Path(out) / "manifest.json").read_text(encoding="utf-8"))
        n = len(doc.get("scenes") or [])
    except (OSError, ValueError, AttributeError):
        n = 0
    print(f"mehs build: interrupted: {out} holds {n} committed scene(s), not every scene asked "
          "for; run the same command again to finish it (committed scenes are kept)",
          file=sys.stderr)
