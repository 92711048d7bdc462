"""`mehs export HS --out DIR` — export an HS cube for spectral rendering.

``per-wavelength``: ``DIR/<prefix>_000.exr …`` one grayscale float EXR per band
plus ``<prefix>_wavelengths.txt/.json``; ``spectral``: ``DIR/<prefix>.exr``,
one multi-channel EXR (Fichet 2021 layout); ``both`` (default).
"""

from __future__ import annotations

from pathlib import Path


def configure(parser) -> None:
    parser.add_argument("hs", metavar="HS",
                        help="HS cube: ENVI .hdr, Specim IQ capture folder or spectral .exr")
    parser.add_argument("--out", required=True, metavar="DIR", help="output folder")
    parser.add_argument("--format", default="both",
                        choices=["per-wavelength", "spectral", "both"],
                        help="one EXR per wavelength, one spectral EXR, or both (default)")
    parser.add_argument("--prefix", default="band",
                        help="file-name prefix (default 'band': band_000.exr …, band.exr)")
    parser.add_argument("--bands", default=None, metavar="SPEC",
                        help="resample first (Gaussian, 10 nm FWHM) to these centres, "
                             "e.g. 400:700:10 (default: keep the cube's bands)")
    parser.add_argument("--half", action="store_true", help="store half floats")
    parser.add_argument("--force", action="store_true",
                        help="replace an earlier export of this --prefix in --out (refused "
                             "without it): its files are replaced once the new export is "
                             "written, and those of the format not written this time removed; "
                             "other files are kept")


def run(args) -> int:
    from mehs.errors import InputError
    from mehs.export import valid_prefix
    from mehs.io import load_cube

    out = Path(args.out)
    valid_prefix(args.prefix)
    if out.exists() and not out.is_dir():
        raise InputError("--out exists and is not a folder", out)
    from mehs.cli._overwrite import refuse_existing
    from mehs.io.atomic import refuse_inside_raw_capture

    refuse_inside_raw_capture(out)

    if out.is_dir():
        # an export is there once complete: its listing (written last) or its spectral file
        # (renamed in whole); band files without a listing are a killed run's, which the
        # same command replaces without --force (foreign band-like files are still refused)
        refuse_existing([out / f"{args.prefix}_wavelengths.json", out / f"{args.prefix}.exr"],
                        args.force)
    cube = load_cube(args.hs)
    if args.bands:
        from mehs.synthesis.resample import parse_bands, resample_cube
        cube = resample_cube(cube, parse_bands(args.bands))
    if args.half:
        _warn_half_precision(cube)
    from mehs.io.lock import OutputLock

    with OutputLock(out, what="mehs export"):   # creates --out; a second run is refused
        written = _write(cube, out, args)
    wl = cube.wavelengths
    print(f"{out}: {len(written)} EXR file(s), {cube.bands} bands {wl[0]:g}..{wl[-1]:g} nm")
    return 0


def _write(cube, out: Path, args) -> list[Path]:
    """Write the export as one set: all of it, or (on an exception) nothing changed.

    The spectral EXR is written to a hidden temporary file first and renamed into place
    only after the per-wavelength set (itself all-or-nothing,
    :func:`mehs.export.export_per_wavelength`) is in place, so a failure in either leaves
    an earlier export whole instead of a new ``<prefix>.exr`` beside an earlier cube's
    bands, or the reverse. Once written, the earlier export's files of the format not
    written this time (``--force``; they are of another cube) are removed.
    """
    import contextlib

    from mehs.export import (export_per_wavelength, export_spectral_exr,
                             remove_per_wavelength_export)
    from mehs.io.atomic import atomic_path

    spectral = args.format in ("spectral", "both")
    per_wl = args.format in ("per-wavelength", "both")
    single = out / f"{args.prefix}.exr"
    written: list[Path] = []
    with contextlib.ExitStack() as staged:
        if spectral:
            tmp = staged.enter_context(atomic_path(single))   # renamed onto it on exit
            export_spectral_exr(cube, tmp, half=args.half, name=single)
        if per_wl:
            written += export_per_wavelength(cube, out, prefix=args.prefix, half=args.half)
    if spectral:
        written.append(single)
    else:
        single.unlink(missing_ok=True)
    if not per_wl:
        remove_per_wavelength_export(out, args.prefix)
    return written


#: Share of the non-zero samples below half's smallest normal above which --half warns.
SUBNORMAL_SHARE_WARN = 1e-3


def _warn_half_precision(cube) -> None:
    """Say on stderr when ``--half`` stores many samples as half subnormals (< 2^-14).

    Half float keeps 11 bits only from 6.1e-5 up: a cube in absolute radiance or of a dim
    scene lost its precision there without a word (a value at 10⁻⁶ keeps 4 bits). The
    export keeps the values as they are (renderers read them as radiance), so it warns.
    """
    import sys

    import numpy as np

    a = np.abs(np.asarray(cube.data, dtype=np.float32))
    nonzero = np.count_nonzero(a)
    tiny = np.count_nonzero((a > 0) & (a < np.float32(2.0 ** -14)))
    if nonzero and tiny > SUBNORMAL_SHARE_WARN * nonzero:
        print(f"mehs export: warning: {100 * tiny / nonzero:.3g} % of the non-zero values of "
              f"{cube.source or 'the cube'} lie below half float's smallest normal (6.1e-5) "
              "and keep less than its 11-bit precision; export 32-bit float (no --half)",
              file=sys.stderr)
