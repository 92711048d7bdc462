"""`mehs fuse` — recover the response curve and merge a bracket into an HDR cube."""

from __future__ import annotations


def configure(parser):
    parser.add_argument("scene", nargs="+",
                        help="a scene folder (scene.json), or two or more Specim IQ folders")
    parser.add_argument("--out", required=True, help="output folder")
    parser.add_argument("--method", default="poisson",
                        choices=["poisson", "inverse-variance", "robertson", "debevec"],
                        help="merge estimator (default: poisson, Hanji et al. 2020)")
    parser.add_argument("--response", default="auto",
                        help="auto | linear | debevec | path of a saved curve (response.json); auto "
                             "(default): linear when the exposure ratios prove the sensor "
                             "linear, else a checked Debevec curve")
    # None: mehs.synthesis.response's DEFAULT_SMOOTHNESS or SMOOTHNESS_CANDIDATES (not
    # imported: the CLI starts without numpy)
    parser.add_argument("--lambda", dest="smoothness", type=float, default=None,
                        help="Debevec smoothness λ (bit-depth independent; default: 100, or "
                             "for a shared curve of a bright bracket one of 100, 300, 1000 "
                             "chosen by its fit to held-out pixels)")
    parser.add_argument("--samples", type=int, default=None,
                        help="pixels sampled per curve (default 2·levels/(exposures−1))")
    parser.add_argument("--per-band", action="store_true",
                        help="one response curve per band instead of one shared curve")
    parser.add_argument("--ghosts", default="detect", choices=["detect", "off", "deghost"],
                        help="flag moving pixels (detect), also take them from one exposure "
                             "(deghost), or skip the test (off) (default: detect)")
    parser.add_argument("--ghost-bins", default="auto", metavar="N",
                        help="adjacent bands summed per term of the ghost test's χ² statistic: "
                             "auto (default: 4 for a linear sensor's cube of ≥ 100 bands and "
                             "≤ 16 exposures, else 1), or N ≥ 1; 1 tests every band alone "
                             "(spectra whose moving features change sign within a few bands). "
                             "N > 1 needs a linear sensor (not --response debevec) and at most "
                             "16 exposures (auto takes 1 otherwise)")
    parser.add_argument("--reference", default="auto",
                        help="exposure index used for ghost pixels with --ghosts deghost (default "
                             "auto: the one with most usable samples there)")
    parser.add_argument("--noise", default="auto", choices=["auto", "recorded"],
                        help="noise model: measured from the bracket by photon transfer across "
                             "exposures (auto, default) or the sensor recorded in scene.json")
    parser.add_argument("--calibration", default=None, metavar="CAL",
                        help="calibration file from `mehs calibrate` (radiance output), or a "
                             "number: a plain factor from DN/ms to radiance")
    parser.add_argument("--saturation", default="auto", metavar="DN",
                        help="raw DN at or above which a sample counts as saturated; auto "
                             "(default): 0.98·(2^bits − 1), lower where the longest exposure "
                             "shows the sensor clipping below it (see summary.json "
                             "saturation_detected)")
    parser.add_argument("--clip-negative", action="store_true",
                        help="clip negative radiance (noise around zero) to 0; by default "
                             "the unbiased signed estimate is kept (clipping biases dark "
                             "pixels upward)")
    parser.add_argument("--seed", type=int, default=0,
                        help="pixel sampling seed (default 0)")
    parser.add_argument("--verify", default="sha256", choices=["sha256", "size", "none"],
                        help="check scene files against scene.json (default sha256)")
    parser.add_argument("--force", action="store_true",
                        help="replace the outputs of an earlier fusion in --out (refused "
                             "without it)")
    parser.add_argument("--allow-partial", action="store_true",
                        help="fuse the complete exposures of a scene whose capture did not "
                             "finish (refused by default; 'mehs capture --resume' finishes it)")


def check_bracket_paths(paths) -> None:
    """Say what a lone path is when it cannot be a bracket, before the loader's generic
    "not a scene folder" (which read as nonsense for a scene's own scene.json)."""
    from pathlib import Path

    from mehs.errors import InputError

    if len(paths) != 1:
        return
    p = Path(paths[0])
    if p.is_file() and p.name == "scene.json":
        raise InputError(f"give the scene folder, not its scene.json: {p.parent}", p)
    if p.is_file():
        raise InputError("a file, not a scene folder or a bracket: give a scene folder "
                         "(scene.json + exposures/) or two or more Specim IQ folders of the "
                         "same view", p)
    if p.is_dir() and not (p / "scene.json").exists() and (
            (p / "capture").is_dir() or (p / "manifest.xml").is_file()):
        raise InputError("one Specim IQ capture is not a bracket: give two or more of the "
                         "same view (shortest exposure first), or the scene folder holding "
                         "them", p)


#: Files ``mehs fuse`` writes into ``--out`` (see :func:`mehs.synthesis.fuse.write_fusion`).
FUSION_FILES = ("radiance.hdr", "mask.png", "confidence.exr", "response.json", "summary.json")


def run(args) -> int:
    import json
    from pathlib import Path

    from mehs.synthesis.bracket import load_bracket
    from mehs.synthesis.fuse import fuse_bracket, write_fusion

    from mehs.io.atomic import check_output_dir

    check_bracket_paths(args.scene)
    check_output_dir(args.out, inputs=args.scene)  # before minutes of fusion, not after
    from mehs.synthesis.merge_types import consistency_bins_value

    args.ghost_bins = consistency_bins_value(args.ghost_bins, what="--ghost-bins")
    from mehs.cli._overwrite import refuse_existing

    if (Path(args.out) / "summary.json").exists():
        refuse_existing([Path(args.out) / n for n in FUSION_FILES], args.force)
    # else: fusion files without the summary (written last) are an unfinished run's, killed
    # while it wrote: this run replaces them, as the same command should finish the job
    cal = args.calibration
    if cal is not None:
        try:
            cal = float(cal)
        except ValueError:
            from mehs.calibration import Calibration

            cal = Calibration.load(cal)   # a bad file fails before the fusion
    paths = args.scene if len(args.scene) > 1 else args.scene[0]
    # the raws are hashed while they are fused; fuse_bracket returns nothing (so nothing
    # is written) unless they match scene.json
    bracket = load_bracket(paths, verify=args.verify, allow_partial=args.allow_partial,
                           defer_verify=True)
    from mehs.errors import InputError

    try:
        ref = args.reference if args.reference == "auto" else int(args.reference)
    except ValueError:
        bracket.check_files()     # a damaged scene is said first, as before
        raise InputError(f"--reference must be 'auto' or an exposure index, "
                         f"got {args.reference!r}") from None
    try:
        sat = None if args.saturation == "auto" else float(args.saturation)
    except ValueError:
        bracket.check_files()
        raise InputError(f"--saturation must be 'auto' or a raw level in DN, "
                         f"got {args.saturation!r}") from None
    import sys
    import warnings

    from mehs.synthesis.fuse import ResponseUndeterminedWarning

    with warnings.catch_warnings():
        # said once below, as a mehs warning, not as a Python warning with a source line
        warnings.simplefilter("ignore", ResponseUndeterminedWarning)
        res = fuse_bracket(bracket, method=args.method, response=args.response,
                           ghosts=args.ghosts, smoothness=args.smoothness, samples=args.samples,
                           seed=args.seed, shared_response=not args.per_band,
                           calibration=cal, reference=ref, noise=args.noise,
                           saturation=sat, clip_negative=args.clip_negative,
                           ghost_bins=args.ghost_bins)
    files = write_fusion(res, args.out)
    for w in res.summary.get("warnings", []):
        print(f"mehs: warning: {w}", file=sys.stderr)
    s = res.summary
    dr = s["dynamic_range_stops"]
    gf = s["ghost_fraction"]
    print(f"{files['radiance']}: {' × '.join(map(str, s['shape']))} float32, "
          f"{s['method']} merge, response {s['response']['method']}, "
          f"DR {'n/a' if dr is None else f'{dr:.1f}'} stops, "
          f"saturated {100 * s['saturated_fraction']:.2f} %, ghosts "
          f"{'not tested' if gf is None else f'{100 * gf:.2f} %'}, unit {s['units']}")
    print(json.dumps({k: str(v) for k, v in files.items()}))
    return 0
