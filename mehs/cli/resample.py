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
    """Refuse an output that is an input, has an unknown suffix, or exists without ``force``."""
    from mehs.errors import InputError

    if out.suffix.lower() not in suffixes:
        raise InputError(f"output must end in {' or '.join(suffixes)}", out)
    for p in inputs:
        if p.exists() and out.resolve() == p.resolve():
            raise InputError("output would overwrite the input", out)
        if p.suffix.lower() == ".hdr" and out.resolve() in (p.with_suffix(".hdr").resolve(),
                                                             p.with_suffix(".raw").resolve(),
                                                             p.with_suffix(".dat").resolve()):
            raise InputError("output would overwrite the input", out)
    if out.exists() and not force:
        raise InputError("output exists (use --force to replace it)", out)


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
    print(f"{out}: {res.lines}×{res.samples}×{res.bands} float32, {wl[0]:g}..{wl[-1]:g} nm "
          f"({args.method}, fwhm {args.fwhm:g} nm) from {cube.bands} bands")
    return 0
