"""`mehs render HS_MAP --out DIR` — spectral image-based lighting on Mitsuba 3 (render extra).

Renders an object under the HS map (reference), under its pseudo-HDR-RGB (RGB renderer),
and under the RGB map up-sampled back to spectra (Smits 1999 as PBRT, Jakob–Hanika as
Mitsuba, and any ``--ssr`` models); writes EXR + PNG renders, ×5 difference images, their
ΔE2000 / relative error in ``render.json`` and ``index.html``. See :mod:`mehs.render`.
"""

from __future__ import annotations


def configure(parser) -> None:
    parser.add_argument("hs_map", metavar="HS_MAP",
                        help="lat-long HS map: ENVI .hdr, spectral .exr, or a per-wavelength "
                             "EXR folder from 'mehs export'")
    parser.add_argument("--out", required=True, metavar="DIR", help="output folder")
    parser.add_argument("--object", default="sphere", metavar="sphere|PATH.obj|PATH.ply",
                        help="object to render (default: a sphere)")
    parser.add_argument("--material", default="thin-film:SiO2:300nm",
                        help="thin-film:SiO2:300nm (default; films top first, e.g. "
                             "thin-film:Al:5nm,SiO2:400nm; '@Al' changes the Si substrate) "
                             "or diffuse[:ρ]")
    parser.add_argument("--spp", type=int, default=128, help="samples per pixel (default 128)")
    parser.add_argument("--size", default="512x512", metavar="WxH", help="image size (default 512x512)")
    parser.add_argument("--seed", type=int, default=0, help="sampler seed (default 0)")
    parser.add_argument("--ssr", nargs="+", default=[], metavar="MODEL",
                        help="also render with maps reconstructed from the RGB map by these SSR "
                             "models (names, module:function, .onnx, .npz, .pt; see mehs evaluate)")
    parser.add_argument("--ssr-input", default="hdr", choices=["hdr", "ldr", "both"],
                        help="what the --ssr models see: the pseudo-HDR-RGB (default), its 8-bit "
                             "LDR-RGB (the paper's LDR-SSR map, highlights clipped), or both")
    parser.add_argument("--methods", default="rgb,smits,jakob",
                        help="comparison renders besides the HS reference (default rgb,smits,jakob)")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")


def run(args) -> int:
    from mehs.cli import progress_bars
    from mehs.render.run import render_comparison
    from mehs.render.scene import RenderSettings, parse_size

    width, height = parse_size(args.size)
    settings = RenderSettings(width=width, height=height, spp=args.spp, seed=args.seed,
                              object=args.object, material=args.material)
    methods = tuple(m.strip() for m in args.methods.split(",") if m.strip())
    inputs = ("hdr", "ldr") if args.ssr_input == "both" else (args.ssr_input,)
    doc = render_comparison(args.hs_map, args.out, settings, ssr=args.ssr, methods=methods,
                            ssr_inputs=inputs, progress=progress_bars(args.no_progress),
                            say=print)
    print(f"{'render':<14}{'mean ΔE2000':>12}{'rel. error':>12}{'SAM (°)':>9}{'time (s)':>10}")
    for r in doc["results"]:
        de, rel, sam = r.get("mean_delta_E2000"), r.get("relative_error"), r.get("mean_sam_deg")
        print(f"{r['name']:<14}{'ref.' if de is None else f'{de:.3f}':>12}"
              f"{'' if rel is None else f'{rel:.4f}':>12}{'' if sam is None else f'{sam:.2f}':>9}"
              f"{r['seconds']:>10.1f}")
    print(f"{args.out}: {len(doc['results'])} renders, page {doc['page']}")
    return 0
