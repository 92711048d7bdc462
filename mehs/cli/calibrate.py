"""`mehs calibrate` — responsivity (DN/ms per unit radiance) from a capture of a known reference."""

from __future__ import annotations


def configure(parser):
    parser.add_argument("capture", nargs="+",
                        help="the reference capture: a scene folder, or Specim IQ folders")
    parser.add_argument("--out", "-o", required=True, help="calibration file to write (JSON)")
    src = parser.add_mutually_exclusive_group(required=True)
    src.add_argument("--source", metavar="CERT",
                     help="calibrated source certificate (CSV: nm, W sr-1 m-2 nm-1[, rel. "
                          "uncertainty]; or ENVI): absolute radiance")
    src.add_argument("--panel", metavar="REFLECTANCE",
                     help="diffuse panel reflectance (CSV or ENVI; a number for a flat panel): "
                          "relative radiance, needs --illuminant")
    parser.add_argument("--source-unit", metavar="UNIT", default=None,
                        help="unit of the --source values when its header does not name it, or "
                             "names it wrongly: e.g. 'uW cm-2 sr-1 nm-1', 'W/(m2 sr um)' "
                             "(default: the header's, else W sr-1 m-2 nm-1, stated)")
    parser.add_argument("--illuminant", metavar="SPD",
                        help="the panel's illuminant: a colour-science name (D65, A, HP1, ...) "
                             "or a CSV/ENVI relative SPD")
    parser.add_argument("--region", default=None,
                        help="where the reference is: 'white' (the white-reference line; "
                             "default with --panel), 'frame' (fills the view; default with "
                             "--source) or 'lines:A-B'")
    parser.add_argument("--response", default="linear",
                        help="response curve to linearise the capture: linear (default) or the "
                             "response.json that the scenes will be fused with")
    parser.add_argument("--camera-id", default=None,
                        help="camera id to record (default: the one in scene.json)")
    parser.add_argument("--no-flat-field", action="store_true",
                        help="one responsivity per band (mean over columns) instead of per column")
    parser.add_argument("--columns", metavar="A-B", default=None,
                        help="with --no-flat-field: the columns (0-based, inclusive) a reference "
                             "narrower than the view fills; a reference leaving columns unlit "
                             "is refused otherwise")
    parser.add_argument("--partial", action="store_true",
                        help="calibrate only the contiguous bands the reference spectra cover "
                             "(e.g. a colour-science illuminant ends at 780 nm); calibrated "
                             "cubes then hold those bands only")
    parser.add_argument("--force", action="store_true", help="replace an existing --out file")


def run(args) -> int:
    from pathlib import Path

    import numpy as np

    from mehs.calibration import (calibrate_panel_relative, calibrate_source_absolute,
                                  load_spectrum)
    from mehs.calibration.spectra import Spectrum
    from mehs.errors import InputError
    from mehs.synthesis.bracket import load_bracket

    out = Path(args.out)
    from mehs.cli._overwrite import check_writable
    from mehs.io.atomic import refuse_inside_raw_capture

    refuse_inside_raw_capture(out)   # a calibration file beside a raw cube changes the capture
    check_writable(out)
    if out.exists() and not args.force:
        raise InputError("exists; use --force to replace it", out)
    if out.exists() and out.is_dir():
        raise InputError("is a folder, give a file name", out)
    if args.panel and not args.illuminant:
        raise InputError("--panel needs --illuminant (the SPD lighting the panel)")
    if args.source and args.illuminant:
        raise InputError("--illuminant goes with --panel, not --source")
    if args.source_unit and not args.source:
        raise InputError("--source-unit goes with --source")
    from mehs.cli.fuse import check_bracket_paths

    check_bracket_paths(args.capture)
    bracket = load_bracket(args.capture if len(args.capture) > 1 else args.capture[0])
    common = dict(response=args.response, per_column=not args.no_flat_field,
                  camera_id=args.camera_id, partial=args.partial, columns=args.columns)
    if args.source:
        spec = load_spectrum(args.source, what="source radiance")
        cal = calibrate_source_absolute(bracket, spec, region=args.region or "frame",
                                        source_unit=args.source_unit, **common)
    else:
        try:
            rho = float(args.panel)
        except ValueError:
            panel = load_spectrum(args.panel, what="panel reflectance")
        else:
            if not 0 < rho <= 1.5:
                raise InputError(f"--panel reflectance must be in (0, 1.5], got {rho}")
            panel = Spectrum(np.array([100.0, 20000.0]), np.array([rho, rho]), f"flat {rho:g}")
        ill = load_spectrum(args.illuminant, what="illuminant SPD")
        cal = calibrate_panel_relative(bracket, panel, ill, region=args.region or "white", **common)
    cal.save(out)
    su = cal.parameters.get("source_unit")
    if su and su.get("from") == "assumed":
        print(f"certificate unit not stated in {args.source}: taken as W sr-1 m-2 nm-1 "
              "(--source-unit to give another)")
    elif su:
        print(f"certificate unit {su['unit']!r} ({su['from']}): values x {su['factor']:g} "
              "to W sr-1 m-2 nm-1")
    r = cal.responsivity
    cw = cal.calibrated_wavelengths
    if not cal.complete:
        print(f"calibrated {cw.size} of {cal.wavelengths.size} bands ({cw[0]:.2f}-{cw[-1]:.2f} nm, "
              "what the reference covers); calibrated cubes hold these bands only")
    print(f"{out}: {cal.method}, unit {cal.unit}, {r.shape[1]} bands × {r.shape[0]} column(s), "
          f"responsivity {np.median(r):.4g} DN/ms per unit (median), uncertainty "
          f"{np.median(cal.uncertainty):.2%} (median), {np.percentile(cal.uncertainty, 95):.2%} (p95)")
    lo, hi = cal.parameters["column_profile"]
    cols = cal.parameters.get("columns")
    where = f"columns {cols[0]}-{cols[1]}" if cols else "columns"
    if cal.responsivity.shape[0] > 1:
        print(f"flat field: {where} at {lo:.3f}-{hi:.3f} of the brightest columns (the reference "
              "is taken as uniform across the slit: its own non-uniformity is in the flat field)")
    else:
        print(f"one responsivity per band from {where} at {lo:.3f}-{hi:.3f} of the brightest; "
              f"their spread ({cal.parameters['column_spread_median']:.2%} median) is in the "
              "uncertainty")
    return 0
