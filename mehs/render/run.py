"""The paper's rendering comparison (§4.4): one object, one HS map, several lightings.

:func:`render_comparison` renders, in one output folder,

==============  ============================================================  =========
name            lighting                                                       renderer
==============  ============================================================  =========
``hs``          the HS map (ground truth, the reference of every difference)   spectral
``rgb``         the map's pseudo-HDR-RGB                                       RGB
``smits``       RGB map up-sampled by Smits 1999, illuminant basis (pbrt-v3)   spectral
``jakob``       RGB map up-sampled by Mitsuba (Jakob & Hanika 2019)            spectral
``ssr-<name>``  pseudo-HDR-RGB map reconstructed by an SSR model (``--ssr``)   spectral
``…-ldr``       the same from the map's 8-bit LDR-RGB (``--ssr-input ldr``)   spectral
==============  ============================================================  =========

and writes per name ``<name>.exr`` (linear sRGB, float32), ``<name>.png`` (exposed like
the reference), spectral renders also ``<name>_spectral.exr`` (Fichet layout), every
non-reference ``<name>_diff_x5.png``; ``env_rgb.png`` (the map), ``render.json`` (settings,
numbers, files) and ``index.html``.
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Callable

import numpy as np

from mehs import __version__
from mehs.errors import InputError
from mehs.io.atomic import make_output_dir, write_json_atomic
from mehs.render.compare import DIFF_GAIN, difference_image, score
from mehs.render.maps import EnvMap, load_envmap, rgb_map, ssr_map
from mehs.render.scene import RenderSettings, import_mitsuba, render_rgb, render_spectral
from mehs.render.smits_pbrt import SmitsPBRT
from mehs.rgb import hdr_rgb, ldr_exposure, ldr_rgb

RENDER_FORMAT = "mehs-render/1"

DESCRIPTIONS = {
    "hs": "spectral rendering with the HS map (reference)",
    "rgb": "RGB rendering with the pseudo-HDR-RGB map",
    "smits": "spectral rendering, RGB map up-sampled by Smits 1999 as pbrt-v3 (illuminant basis)",
    "jakob": "spectral rendering, RGB map up-sampled by Jakob & Hanika 2019 (Mitsuba's envmap)",
}


def _describe(name: str) -> str:
    if name in DESCRIPTIONS:
        return DESCRIPTIONS[name]
    src = "8-bit LDR-RGB" if name.endswith("-ldr") else "pseudo-HDR-RGB"
    return f"spectral rendering, map reconstructed from the {src} by SSR model {name[4:]}"


def _png(path: Path, rgb: np.ndarray, exposure: float) -> str:
    from mehs.preview import write_png

    img, _ = ldr_rgb(np.clip(rgb, 0.0, None), exposure=exposure)
    write_png(path, img)
    return path.name


def ldr_map(rgb: np.ndarray) -> np.ndarray:
    """The 8-bit LDR version of an RGB map, linearised back to the HDR scale ``(H, W, 3)``."""
    from mehs.ssr.data import srgb_decode_8bit

    img, exposure = ldr_rgb(rgb)
    return srgb_decode_8bit(img) / np.float32(exposure)


def _exposure(reference_rgb: np.ndarray) -> float:
    try:
        return float(ldr_exposure(reference_rgb))
    except InputError:
        return 1.0


def render_comparison(hs_map: str | Path | EnvMap, out: str | Path, settings: RenderSettings,
                      *, ssr: list[str] = (), methods: tuple[str, ...] = ("rgb", "smits", "jakob"),
                      ssr_inputs: tuple[str, ...] = ("hdr",),
                      progress: bool = True, say: Callable[[str], None] = lambda s: None) -> dict:
    """Render the comparison into ``out`` and return the ``render.json`` document.

    Parameters
    ----------
    hs_map
        An :class:`EnvMap` or a path :func:`~mehs.render.maps.load_envmap` reads.
    settings
        Size, spp, seed, object and material.
    ssr
        SSR model specs (:func:`mehs.ssr.models.load_model`): each renders as
        ``ssr-<name>`` from the map's pseudo-HDR-RGB.
    methods
        Which of ``rgb``, ``smits``, ``jakob`` to render besides ``hs``.
    ssr_inputs
        What the SSR models see: ``hdr`` (the pseudo-HDR-RGB) and/or ``ldr`` (its 8-bit
        LDR-RGB, :func:`mehs.rgb.ldr_rgb`, decoded and divided by its exposure — the
        paper's LDR-SSR map of Fig. 11, whose highlights are clipped).
    progress
        Show a tqdm bar over all samples of all renders.
    """
    import_mitsuba()
    from mehs.ssr.models import load_model

    unknown = [m for m in methods if m not in ("rgb", "smits", "jakob")]
    if unknown:
        raise InputError(f"unknown render method(s) {unknown}; use rgb, smits, jakob")
    bad = [i for i in ssr_inputs if i not in ("hdr", "ldr")]
    if bad or not ssr_inputs:
        raise InputError(f"SSR input must be hdr and/or ldr, got {list(ssr_inputs)}")
    env = hs_map if isinstance(hs_map, EnvMap) else load_envmap(hs_map)
    rgb_env = rgb_map(env)
    models = []
    for spec in ssr:
        model = load_model(spec)
        models.append((f"ssr-{getattr(model, 'name', None) or Path(str(spec)).stem}", str(spec), model))
    inputs = [Path(str(hs_map))] if not isinstance(hs_map, EnvMap) else []
    out = make_output_dir(out, inputs=[p for p in inputs if p.is_dir()])

    jobs: list[tuple[str, str, object]] = [("hs", "spectral", env)]
    for m in methods:
        if m == "rgb":
            jobs.append(("rgb", "rgb", rgb_env))
        elif m == "smits":
            jobs.append(("smits", "spectral", ssr_map(rgb_env, SmitsPBRT(), "smits")))
        else:
            jobs.append(("jakob", "jakob", rgb_env))
    for name, spec, model in models:
        for inp in ssr_inputs:
            label = name if inp == "hdr" else f"{name}-ldr"
            jobs.append((label, "spectral", ssr_map(rgb_env if inp == "hdr" else ldr_map(rgb_env),
                                                    model, label)))

    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=settings.spp * len(jobs), unit="spp", desc="render", leave=False)
    step = (lambda n: bar.update(n)) if bar is not None else None

    wl = np.asarray(settings.bands, dtype=np.float64)
    images: dict[str, dict] = {}
    timings: dict[str, float] = {}
    try:
        for name, kind, light in jobs:
            say(f"render {name}: {_describe(name)}")
            if bar is not None:
                bar.set_description(f"render {name}")
            t0 = time.perf_counter()
            if kind == "rgb":
                rgb, spectra = render_rgb(settings, light, progress=step), None
            elif kind == "jakob":
                spectra = render_spectral(settings, rgb_map=light, progress=step)
                rgb = hdr_rgb(spectra, wl)
            else:
                spectra = render_spectral(settings, hs_map=light, progress=step)
                rgb = hdr_rgb(spectra, wl)
            timings[name] = time.perf_counter() - t0
            images[name] = {"rgb": np.asarray(rgb, np.float32), "spectra": spectra,
                            "neg": getattr(light, "metadata", {}).get("negative_fraction")}
    finally:
        if bar is not None:
            bar.close()
    return _write_outputs(out, env, rgb_env, settings, images, timings, [m[1] for m in models],
                          ssr_inputs)


def _write_outputs(out: Path, env: EnvMap, rgb_env: np.ndarray, settings: RenderSettings,
                   images: dict, timings: dict, ssr_specs: list[str], ssr_inputs) -> dict:
    from mehs.io.exr import write_exr_rgb, write_exr_spectral
    from mehs.render.page import write_page

    wl = np.asarray(settings.bands, dtype=np.float64)
    ref = images["hs"]
    exposure = _exposure(ref["rgb"])
    env_exposure = _exposure(rgb_env)
    files = {"env_rgb.png": _png(out / "env_rgb.png", rgb_env, env_exposure)}
    results = []
    for name, im in images.items():
        entry = {"name": name, "description": _describe(name),
                 "seconds": round(timings[name], 3),
                 "exr": write_exr_rgb(out / f"{name}.exr", im["rgb"], half=False).name,
                 "png": _png(out / f"{name}.png", im["rgb"], exposure)}
        if im["spectra"] is not None:
            entry["spectral_exr"] = write_exr_spectral(out / f"{name}_spectral.exr",
                                                       im["spectra"], wl).name
        if im["neg"] is not None:
            entry["map_negative_fraction"] = im["neg"]
        if name != "hs":
            entry.update(score(im["rgb"], ref["rgb"], im["spectra"], ref["spectra"]))
            diff = difference_image(im["rgb"], ref["rgb"])
            entry["diff_png"] = _png(out / f"{name}_diff_x{DIFF_GAIN:g}.png", diff, exposure)
        results.append(entry)
    doc = {
        "format": RENDER_FORMAT, "software_version": __version__,
        "map": {"source": env.source, "shape": list(env.shape),
                "wavelengths_nm": [float(w) for w in env.wavelengths],
                # the renders are in these units; a dataset cube's 2^-k was divided out
                "units": env.metadata.get("units"),
                "stored_radiance_scale": env.metadata.get("radiance_scale")},
        "settings": {"width": settings.width, "height": settings.height, "spp": settings.spp,
                     "seed": settings.seed, "object": settings.object,
                     "material": settings.material, "bands_nm": [float(b) for b in wl]},
        "reference": "hs", "difference_gain": DIFF_GAIN, "exposure": exposure,
        "ssr_models": ssr_specs, "ssr_inputs": list(ssr_inputs), "results": results, "files": files,
    }
    doc["page"] = write_page(out, doc).name
    write_json_atomic(out / "render.json", doc)
    return doc
