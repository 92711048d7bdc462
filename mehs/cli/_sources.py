"""``--format`` and the reading options of public SSR datasets, shared by the SSR commands."""

from __future__ import annotations

# spelled out, not imported from mehs.io.ssr_datasets, to keep the parsers' import light;
# tests/test_ssr_harvard_reader.py checks it lists every format
FORMAT_CHOICES = ("auto", "arad1k", "arad", "icvl", "cave", "kaust", "harvard", "kaist", "cassi28")


def add_source_arguments(parser) -> None:
    """Options for reading ARAD-1K, ARAD/BGU-HS, ICVL, CAVE, KAUST, Harvard, KAIST and CASSI-28
    folders directly."""
    parser.add_argument("--format", dest="source_format", choices=FORMAT_CHOICES, default="auto",
                        help="dataset layout: auto (a mehs dataset, a folder of pairs, or a public "
                             "SSR dataset detected by its files) or a public format "
                             "(default: %(default)s)")
    parser.add_argument("--hs-bands", default="visible", metavar="BANDS",
                        help="public datasets: bands kept, 'visible' (400–700 nm), 'all', or "
                             "start:stop:step / a list in nm (default: %(default)s)")
    parser.add_argument("--hs-crop", default=None, metavar="HxW",
                        help="public datasets: central crop of every scene, e.g. 256x256")
    parser.add_argument("--hs-scale", type=float, default=1.0,
                        help="public datasets: multiply the stored values (default 1: as stored)")
    parser.add_argument("--rgb-encoding", choices=("auto", "linear", "srgb"), default="auto",
                        help="public datasets: how their own 8-bit RGB images encode light; auto: "
                             "linear for ARAD-1K and ARAD/BGU-HS (the NTIRE challenges' camera "
                             "projections, no tone curve), sRGB for the others "
                             "(default: %(default)s)")
    parser.add_argument("--harvard-lbl", choices=("zero-excluded", "nonzero-excluded", "ignore"),
                        default="zero-excluded",
                        help="Harvard: which pixels of 'lbl' are excluded as moving objects "
                             "(default: %(default)s, as public loaders read it; the dataset's "
                             "own statement could not be checked)")
    parser.add_argument("--harvard-calib", choices=("none", "divide", "multiply"),
                        default="none",
                        help="Harvard: apply the dataset's calib.txt per band (public code "
                             "disagrees on the direction; default: %(default)s, 'ref' as "
                             "stored)")


def apply_source_arguments(args, dataset) -> None:
    """Record the chosen format and options for ``dataset`` (before it is listed)."""
    import math

    from mehs.errors import InputError
    from mehs.io.ssr_datasets import SourceOptions

    encoding = getattr(args, "rgb_encoding", "auto")
    lbl = getattr(args, "harvard_lbl", "zero-excluded")
    calib = getattr(args, "harvard_calib", "none")
    explicit = (args.source_format != "auto" or args.hs_bands != "visible" or args.hs_crop
                or args.hs_scale != 1.0 or encoding != "auto" or lbl != "zero-excluded"
                or calib != "none")
    if not explicit:
        return
    if not (math.isfinite(args.hs_scale) and args.hs_scale > 0):
        raise InputError(f"--hs-scale must be positive and finite, got {args.hs_scale}")
    bands = args.hs_bands
    if bands not in ("visible", "all"):
        from mehs.synthesis.resample import parse_bands

        bands = tuple(float(b) for b in parse_bands(bands))
    crop = None
    if args.hs_crop:
        try:
            crop = tuple(int(v) for v in args.hs_crop.lower().split("x"))
            if len(crop) != 2 or min(crop) < 1:
                raise ValueError
        except ValueError:
            raise InputError(f"--hs-crop must be HxW pixels, e.g. 256x256, got {args.hs_crop!r}") from None
    from mehs.ssr.sources import detect_format, remember_source

    fmt = args.source_format
    if fmt == "auto":
        fmt = detect_format(dataset)
        if fmt is None:
            raise InputError("--hs-bands/--hs-crop/--hs-scale/--rgb-encoding/--harvard-* "
                             "apply to public SSR datasets, and "
                             "this folder is not one (give --format)", dataset)
    remember_source(dataset, fmt, SourceOptions(bands=bands, crop=crop, scale=float(args.hs_scale),
                                                rgb_encoding=encoding, harvard_lbl=lbl,
                                                harvard_calib=calib))
