"""`mehs resample IN OUT` — resample a cube to a target band set (default 400:700:10).

IN is anything :func:`mehs.io.load_cube` opens (ENVI, Specim IQ folder, spectral
EXR). OUT ending in ``.hdr`` is written as ENVI float32 (bil, ``.dat``); OUT
ending in ``.exr`` as a spectral OpenEXR (Fichet 2021 layout).
"""

from __future__ import annotations

from pathlib import Path


def configure(parser) -> None:
    parser.add_argument("input", metavar="IN",
                        help="ENVI .hdr/data file, Specim IQ capture folder or spectral .exr")
    parser.add_argument("output", metavar="OUT", help="output .hdr (ENVI float32) or .exr")
    parser.add_argument("--bands", default="400:700:10", metavar="SPEC",
                        help="target centres in nm: start:stop:step (stop included) or a "
                             "comma list (default 400:700:10 = 31 bands)")
    parser.add_argument("--method", default="gaussian", choices=["gaussian", "linear", "box"],
                        help="gaussian spectral responses (SPy BandResampler construction; "
                             "default), linear interpolation or box averaging")
    parser.add_argument("--fwhm", type=float, default=10.0, metavar="NM",
                        help="target band FWHM in nm for gaussian/box (default 10)")
    parser.add_argument("--half", action="store_true", help="EXR output: store half floats")
    parser.add_argument("--force", action="store_true", help="replace an existing OUT")


def check_output(out: Path, inputs: list[Path], suffixes: tuple[str, ...], force: bool) -> None:
    """Refuse an output that would replace an input's files, lies in a raw capture, has an
    unknown suffix, or exists without ``force``."""
    from mehs.errors import InputError
    from mehs.io.atomic import refuse_inside_raw_capture

    if out.suffix.lower() not in suffixes:
        raise InputError(f"output must end in {' or '.join(suffixes)}", out)
    written = {f.resolve() for f in _files_of(out, output=True)}
    for p in inputs:
        if p.is_dir():
            src = p.resolve()
            if any(src == f or src in f.parents for f in written):
                raise InputError(f"output would be written inside the input folder {p}", out)
        elif written & {f.resolve() for f in _files_of(p, output=False)}:
            raise InputError("output would overwrite the input", out)
    refuse_inside_raw_capture(out)
    if out.exists() and not force:
        raise InputError("output exists (use --force to replace it)", out)


def _files_of(path: Path, *, output: bool) -> list[Path]:
    """The files an ENVI pair at ``path`` (its header or its data file) is made of; for an
    output also the data file it writes and any old data file its rewrite removes."""
    from mehs.errors import MehsError
    from mehs.io.envi import data_file_candidates, find_header_file

    files = [path]
    if output:
        if path.suffix.lower() == ".hdr":
            files += [path.with_suffix(".dat"), *data_file_candidates(path)]
        return files
    try:
        hdr = path if path.suffix.lower() == ".hdr" else find_header_file(path)
    except (MehsError, OSError):
        return files          # not an ENVI pair (an EXR, or no header): the file alone
    return files + [hdr, *data_file_candidates(hdr)]


def run(args) -> int:
    from mehs.io import load_cube
    from mehs.io.envi import write_envi
    from mehs.io.exr import write_exr_spectral
    from mehs.synthesis.resample import parse_bands, resample_cube

    out = Path(args.output)
    check_output(out, [Path(args.input)], (".hdr", ".exr"), args.force)
    target = parse_bands(args.bands)
    cube = load_cube(args.input)
    res = resample_cube(cube, target, method=args.method, fwhm=args.fwhm)
    if out.suffix.lower() == ".exr":
        write_exr_spectral(out, res, half=args.half)
    else:
        write_envi(out, res, dtype="float32", interleave="bil", data_ext=".dat")
    wl = res.wavelengths
    # linear interpolation has no band width: printing --fwhm's default would claim one
    how = args.method if args.method == "linear" else f"{args.method}, fwhm {args.fwhm:g} nm"
    print(f"{out}: {res.lines}×{res.samples}×{res.bands} float32, {wl[0]:g}..{wl[-1]:g} nm "
          f"({how}) from {cube.bands} bands")
    return 0
