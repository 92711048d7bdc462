"""`mehs rgb HS --out DIR` — pseudo-HDR-RGB (EXR), LDR-RGB (PNG) and a preview of an HS cube.

Writes ``DIR/hdr_rgb.exr`` (half-float linear sRGB, unnormalised; a cube out of half
float's range is stored times a power of two, ``mehsRadianceScale`` in its header and
``radiance_scale`` in ``rgb.json``, as ``mehs build`` stores its scenes),
``DIR/ldr_rgb.png`` (exposed, clipped, sRGB-encoded 8-bit), ``DIR/preview.png``
(Reinhard 2002 global tone mapping) and ``DIR/rgb.json`` (exposure used and
the rules). A cube not on the 31 bands 400:700:10 is first resampled to them
(Gaussian, 10 nm FWHM) unless ``--no-resample``.
"""

from __future__ import annotations

from pathlib import Path


def configure(parser) -> None:
    parser.add_argument("hs", metavar="HS",
                        help="HS cube: ENVI .hdr, Specim IQ capture folder or spectral .exr")
    parser.add_argument("--out", required=True, metavar="DIR", help="output folder")
    parser.add_argument("--ldr-exposure", type=float, default=None, metavar="X",
                        help="multiply the HDR image by X before clipping (default: average "
                             "metering, the log-average luminance maps to 18 %% grey)")
    parser.add_argument("--no-resample", action="store_true",
                        help="use the cube's own bands (inside 360-830 nm) instead of "
                             "resampling to 400:700:10")
    parser.add_argument("--key", type=float, default=0.18,
                        help="Reinhard key for preview.png (default 0.18)")
    parser.add_argument("--force", action="store_true",
                        help="replace the images of an earlier run in --out (refused without it)")
    parser.add_argument("--float", dest="half", action="store_false",
                        help="store hdr_rgb.exr as 32-bit float instead of half")


def run(args) -> int:
    import numpy as np

    from mehs.io import load_cube
    from mehs.io.atomic import write_json_atomic
    from mehs.io.exr import write_exr_rgb
    from mehs.preview import tonemap, write_png
    from mehs.rgb import LDR_EXPOSURE_RULE, WAVELENGTHS_31, hdr_rgb, ldr_rgb

    out = Path(args.out)
    if out.exists() and not out.is_dir():
        from mehs.errors import InputError
        raise InputError("--out exists and is not a folder", out)
    from mehs.cli._overwrite import check_writable, refuse_existing, refuse_foreign_folder
    from mehs.io.atomic import refuse_inside_raw_capture

    own = ("hdr_rgb.exr", "ldr_rgb.png", "preview.png", "rgb.json")
    refuse_inside_raw_capture(out)
    refuse_foreign_folder(out, own, force=args.force, what="mehs rgb's images")
    if (out / "rgb.json").exists():
        refuse_existing([out / n for n in own], args.force)
    # else: images without rgb.json (written last) are a run's killed while it wrote: the
    # same command replaces them
    check_writable(out)
    cube = load_cube(args.hs)
    resampled = False
    if not args.no_resample and not (cube.bands == WAVELENGTHS_31.size
                                     and np.allclose(cube.wavelengths, WAVELENGTHS_31)):
        from mehs.synthesis.resample import resample_cube
        cube = resample_cube(cube, WAVELENGTHS_31, method="gaussian", fwhm=10.0)
        resampled = True
    hdr = hdr_rgb(cube)
    ldr, exposure = ldr_rgb(hdr, exposure=args.ldr_exposure)
    # every image is computed before the first is written, so a bad option
    # (e.g. --key 0) cannot leave a half-written output folder
    preview = tonemap(hdr, "reinhard", key=args.key)
    stored, scale, total = _stored_scale(cube, hdr, half=args.half)
    header = {} if total is None else {"mehsRadianceScale": total}
    from mehs.io.lock import OutputLock

    with OutputLock(out, what="mehs rgb"):   # creates --out; a second run is refused
        from mehs.io.atomic import unlink_durable

        # rgb.json is the commit point: gone before the first image is replaced, so that a
        # kill half-way never leaves it describing a mix of two runs' images
        unlink_durable(out / "rgb.json")
        write_exr_rgb(out / "hdr_rgb.exr", stored, half=args.half, header=header)
        write_png(out / "ldr_rgb.png", ldr)
        write_png(out / "preview.png", preview)
        write_json_atomic(out / "rgb.json", {
            "source": str(args.hs),
            "resampled_to_31_bands": resampled,
            "wavelengths": cube.wavelengths.tolist(),
            "xyz_scale": "1/sum(ybar)",
            "hdr_rgb": {"file": "hdr_rgb.exr", "encoding": "linear sRGB (IEC 61966-2-1), "
                        "negatives clipped, unnormalised", "half": bool(args.half),
                        # stored = RGB of the cube's radiance × radiance_scale (null: 1,
                        # in the cube's own units)
                        "radiance_scale": total},
            # exposure of the stored EXR values: png = encode(clip(exposure · exr))
            "ldr_rgb": {"file": "ldr_rgb.png", "exposure": exposure / scale,
                        "rule": "given by --ldr-exposure" if args.ldr_exposure is not None else
                        LDR_EXPOSURE_RULE,
                        "encoding": "clip [0,1], sRGB OETF, rint(255 v)"},
            "preview": {"file": "preview.png", "tonemap": "Reinhard2002 global", "key": args.key},
        })
    print(f"{out}: hdr_rgb.exr{f' (stored × {total:g})' if total is not None else ''}, "
          f"ldr_rgb.png (exposure {exposure:.6g}), preview.png"
          f"{' (resampled to 31 bands)' if resampled else ''}")
    return 0


def _stored_scale(cube, hdr, *, half: bool):
    """``(stored, scale, total)``: the RGB as written, the power of two applied here, and
    the factor the file's values carry against the radiance (``mehsRadianceScale``; None
    when it is 1 and the cube carried none).

    A half-float EXR keeps 11 bits only between 2^-14 and 65504: a cube brighter or
    dimmer than that (DN/ms light sources, absolute radiance of a dim scene) is stored
    times the power of two :func:`mehs.dataset.cube_figures.half_float_scale` picks, as
    ``mehs build`` does; a dataset cube's own ``mehs radiance scale`` is carried on, or
    the EXR's values were 2^k off without a word.
    """
    import numpy as np

    from mehs.dataset.cube_figures import half_float_scale, luminance_low_end
    from mehs.export import radiance_scale
    from mehs.rgb import spectra_to_XYZ

    own = radiance_scale(cube)
    scale = 1.0
    if half and hdr.size:
        y = spectra_to_XYZ(np.asarray(cube.data, dtype=np.float32), cube.wavelengths)[..., 1]
        scale = half_float_scale(float(hdr.max()),
                                 luminance_low_end(hdr, signed_luminance=y))
    stored = hdr * np.float32(scale) if scale != 1.0 else hdr
    total = (1.0 if own is None else own) * scale
    return stored, scale, (None if own is None and scale == 1.0 else total)
