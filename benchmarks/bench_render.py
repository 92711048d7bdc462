"""Rendering benchmark: seconds per sample-per-pixel at 256×256, HS path vs RGB path (render extra).

Usage: python benchmarks/bench_render.py [--quick] [--size N] [--spp K] [--material SPEC]

One scene, one run: a sphere (default 300 nm SiO₂ on Si) under the simulator's sodium-lamp
scene used as a 64×128 lat-long map, rendered by Mitsuba 3 (``scalar_*`` variants) as

- "hs (HSEnvmap, spectral)": the HS map through mehs's Python spectral emitter — the path
  ``mehs render`` uses for the reference and every SSR map;
- "rgb (envmap, RGB)": the reference, Mitsuba's C++ ``envmap`` with the pseudo-HDR-RGB in the
  RGB variant (what an RGB renderer costs);
- "jakob (envmap, spectral)": Mitsuba's C++ ``envmap`` in the spectral variant (the cost of
  spectral rendering itself, without a Python emitter).

The material's BSDF is the same Python plugin in all three (diffuse: Mitsuba's own). The
ratio column is "this path's time / the RGB path's time" (how many times slower).
"""

from __future__ import annotations

import argparse
import sys
import time

import numpy as np


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="128×128, 1 spp")
    ap.add_argument("--size", type=int, default=256, help="image side in pixels (default 256)")
    ap.add_argument("--spp", type=int, default=2, help="samples per pixel per render (default 2)")
    ap.add_argument("--material", default="thin-film:SiO2:300nm")
    args = ap.parse_args(argv)
    size, spp = (128, 1) if args.quick else (args.size, args.spp)
    try:
        from mehs.render.scene import RenderSettings, import_mitsuba, render_rgb, render_spectral
        import_mitsuba()
    except Exception as exc:  # noqa: BLE001 - report and exit cleanly
        print(f"bench_render: {exc}", file=sys.stderr)
        return 2
    from mehs.capture.scene import make_scene
    from mehs.render.maps import EnvMap, rgb_map
    from mehs.rgb import WAVELENGTHS_31

    sc = make_scene("lamp", lines=64, samples=128, wavelengths=WAVELENGTHS_31, illuminant="D65",
                    light_source="HP1", source_ratio=300.0, seed=0)
    env = EnvMap(np.asarray(sc.radiance, np.float32), WAVELENGTHS_31, "sodium-lamp scene")
    rgb = rgb_map(env)
    s = RenderSettings(width=size, height=size, spp=spp, material=args.material)
    runs = [("rgb (envmap, RGB)", lambda: render_rgb(s, rgb)),
            ("hs (HSEnvmap, spectral)", lambda: render_spectral(s, hs_map=env)),
            ("jakob (envmap, spectral)", lambda: render_spectral(s, rgb_map=rgb))]
    # warm-up: load both variants and the plugins once, outside the timings
    warm = RenderSettings(width=8, height=8, spp=1, material=args.material)
    render_rgb(warm, rgb)
    render_spectral(warm, hs_map=env)
    times = {}
    for name, fn in runs:
        t0 = time.perf_counter()
        fn()
        times[name] = (time.perf_counter() - t0) / spp
    ref = times["rgb (envmap, RGB)"]
    print(f"{size}×{size} pixels, {spp} spp, material {args.material}, map 64×128×31")
    print(f"{'path':<28}{'s per spp':>11}{'× RGB path':>12}")
    for name, t in times.items():
        print(f"{name:<28}{t:>11.3f}{t / ref:>12.2f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
