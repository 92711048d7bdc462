"""Render an object under an environment map with Mitsuba 3 (optional extra ``mehs[render]``).

Four ways to light the same object (paper §4.4, Figs. 11–14):

``hs``       spectral rendering (``scalar_spectral``) with the HS map through
             :class:`~mehs.render.plugins.HSEnvmap` — the ground truth;
``rgb``      RGB rendering (``scalar_rgb``): Mitsuba's ``envmap`` with the map's
             pseudo-HDR-RGB, the material as linear-sRGB reflectance;
``jakob``    spectral rendering with Mitsuba's own ``envmap`` fed the RGB map, which
             up-samples each pixel with Jakob & Hanika 2019 (× D65, as Mitsuba does for
             emitters);
``smits``    spectral rendering with the RGB map up-sampled as pbrt-v3 does for lights
             (Smits 1999 with the illuminant basis, :mod:`mehs.render.smits_pbrt`);
``<model>``  spectral rendering with an HS map reconstructed from the RGB map by an SSR
             model.

Spectral renders are recorded with Mitsuba's ``specfilm``: one channel per output band,
a narrow (0.2 nm) box response at each centre (400, 410, … 700 nm by default), divided by
its width, so a pixel holds the radiance at the band centre — the paper's 31 monochrome
renders in one pass (a wide box would average the map's linearly interpolated spectrum
over the box and bias spiky spectra such as HP1's); they are shown through :func:`mehs.rgb.hdr_rgb` exactly like
the RGB map was made, so the RGB and spectral images are directly comparable.

Shapes: spectral images ``(H, W, B)`` float32, RGB images ``(H, W, 3)`` float32.

References
----------
- Jakob, W. et al. Mitsuba 3 renderer (2022), https://mitsuba.readthedocs.io
- Jakob, W. & Hanika, J. (2019). A low-dimensional function space for efficient
  spectral upsampling. CGF 38(2).
- Smits, B. (1999). An RGB-to-spectrum conversion for reflectances. JGT 4(4).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from mehs.errors import InputError, MehsError
from mehs.render.maps import EnvMap
from mehs.rgb import WAVELENGTHS_31

SPECTRAL_VARIANT = "scalar_spectral"
RGB_VARIANT = "scalar_rgb"


class RenderUnavailable(MehsError):
    """Mitsuba 3 is not installed (``pip install -e ".[render]"``)."""


def import_mitsuba():
    """Import Mitsuba 3 or raise :class:`RenderUnavailable` with the install step."""
    try:
        import mitsuba as mi
    except ImportError as exc:
        raise RenderUnavailable(f"rendering needs Mitsuba 3 ({exc}); install it with "
                                "python -m pip install -e \".[render]\"") from None
    for v in (SPECTRAL_VARIANT, RGB_VARIANT):
        if v not in mi.variants():
            raise RenderUnavailable(f"this Mitsuba build lacks the {v} variant")
    return mi


@dataclass(frozen=True)
class RenderSettings:
    """Image size, samples per pixel, seed, the object and its material."""

    width: int = 64
    height: int = 64
    spp: int = 16
    seed: int = 0
    object: str = "sphere"
    material: str = "thin-film:SiO2:300nm"
    fov: float = 30.0
    max_depth: int = 8
    bands: tuple[float, ...] = tuple(float(w) for w in WAVELENGTHS_31)
    band_width: float = 0.2

    def __post_init__(self):
        if self.width < 1 or self.height < 1:
            raise InputError(f"image size must be positive, got {self.width}x{self.height}")
        if self.spp < 1:
            raise InputError(f"--spp must be ≥ 1, got {self.spp}")
        # fail before any output folder is made or any render starts
        from mehs.render.materials import parse_material

        parse_material(self.material)
        _shape_dict(self.object)


def parse_size(text: str) -> tuple[int, int]:
    """``"512x256"`` → ``(512, 256)`` (width, height); ``"64"`` → square."""
    try:
        parts = [int(p) for p in str(text).lower().split("x")]
    except ValueError:
        raise InputError(f"--size {text!r}: use WIDTHxHEIGHT, e.g. 512x512") from None
    if len(parts) == 1:
        parts *= 2
    if len(parts) != 2 or min(parts) < 1 or max(parts) > 16384:
        raise InputError(f"--size {text!r}: use WIDTHxHEIGHT with 1..16384 pixels")
    return parts[0], parts[1]


# -- scene pieces -----------------------------------------------------------------------

def _shape_dict(obj: str) -> dict:
    if obj == "sphere":
        return {"type": "sphere", "center": [0.0, 0.0, 0.0], "radius": 1.0}
    p = Path(obj)
    ext = p.suffix.lower()
    if ext not in (".obj", ".ply"):
        raise InputError("--object must be 'sphere' or a .obj/.ply mesh", p)
    if not p.is_file():
        raise InputError("mesh file does not exist", p)
    return {"type": ext[1:], "filename": str(p.resolve()), "face_normals": False}


def _is_prime_square(n: int) -> bool:
    r = int(round(n ** 0.5))
    return r * r == n and r >= 2 and all(r % q for q in range(2, int(r ** 0.5) + 1))


def _sampler(spp: int) -> str:
    # Orthogonal-array sampling stratifies the wavelength dimension too, which cuts the
    # per-band noise of a spectral film by ~1.5x at equal spp (measured); Mitsuba requires a prime-square count.
    return "orthogonal" if _is_prime_square(spp) else "independent"


def render_passes(spp: int) -> list[int]:
    """Equal passes (≤ 8) whose sum is ``spp``: a long render reports progress per pass."""
    n = max(d for d in range(1, 9) if spp % d == 0) if spp >= 16 else 1
    return [spp // n] * n


def _camera(mi, shape: dict, s: RenderSettings, film: dict) -> dict:
    pass_spp = render_passes(s.spp)[0]
    # frame the object: look along +z at its bounding sphere so it fills ~70 % of the view
    obj = mi.load_dict(shape)
    bbox = obj.bbox()
    center = np.array([bbox.center()[i] for i in range(3)], dtype=np.float64)
    if shape["type"] == "sphere":
        radius = float(shape["radius"])
    else:  # the bounding box's circumsphere
        radius = float(np.linalg.norm(np.array([bbox.extents()[i] for i in range(3)]))) / 2
    if not np.isfinite(radius) or radius <= 0:
        raise InputError("the object is empty or degenerate", shape.get("filename"))
    dist = radius / np.sin(np.radians(s.fov / 2)) / 0.7
    origin = center - np.array([0.0, 0.0, dist])
    return {"type": "perspective", "fov": s.fov, "fov_axis": "smaller",
            "near_clip": max(1e-3, 1e-3 * dist), "far_clip": 1e4 * dist,
            "to_world": mi.ScalarTransform4f().look_at(origin=origin.tolist(),
                                                       target=center.tolist(), up=[0, 1, 0]),
            "sampler": {"type": _sampler(pass_spp), "sample_count": pass_spp, "seed": s.seed},
            "film": film}


def _specfilm(s: RenderSettings) -> dict:
    film = {"type": "specfilm", "width": s.width, "height": s.height,
            "rfilter": {"type": "box"}, "component_format": "float32"}
    h = s.band_width / 2
    for i, c in enumerate(s.bands):
        # a box of width band_width around c (an irregular spectrum is 0 outside its nodes)
        film[f"band{i:03d}"] = {"type": "irregular",
                                "wavelengths": f"{c - h}, {c + h}", "values": "1, 1"}
    return film


def _rgbfilm(s: RenderSettings) -> dict:
    return {"type": "hdrfilm", "width": s.width, "height": s.height, "pixel_format": "rgb",
            "rfilter": {"type": "box"}, "component_format": "float32"}


def _bsdf(mi, material: str, spectral: bool):
    from mehs.render.materials import TABLE_COS, TABLE_WAVELENGTHS, parse_material, rgb_table, spectral_table
    from mehs.render.plugins import plugin_classes

    kind, value = parse_material(material)
    if kind == "diffuse":
        return {"type": "diffuse", "reflectance": {"type": "spectrum" if spectral else "rgb",
                                                  "value": value if spectral else [value] * 3}}
    _, ThinFilm = plugin_classes(SPECTRAL_VARIANT if spectral else RGB_VARIANT)
    if spectral:
        return ThinFilm(mi.Properties(), table=spectral_table(value), cos_theta=TABLE_COS,
                        wavelengths=TABLE_WAVELENGTHS)
    return ThinFilm(mi.Properties(), table=rgb_table(value), cos_theta=TABLE_COS)


def _rgb_envmap(mi, rgb: np.ndarray) -> dict:
    rgb = np.ascontiguousarray(np.asarray(rgb, dtype=np.float32))
    return {"type": "envmap", "bitmap": mi.Bitmap(rgb, mi.Bitmap.PixelFormat.RGB)}


def _render(mi, scene_dict: dict, s: RenderSettings, progress=None) -> np.ndarray:
    import drjit as dr

    mi.set_log_level(mi.LogLevel.Error)
    scene = mi.load_dict(scene_dict)
    # Mitsuba does not call set_scene on Python emitters: HSEnvmap would keep its unit
    # bounding sphere and end shadow rays 2 units out, so occluders farther away (a mesh
    # larger than that) would let the map's light leak through
    for emitter in scene.emitters():
        if type(emitter).__module__ == "mehs.render.plugins":
            emitter.set_scene(scene)
    # Python plugins run under the GIL: render threads would only queue for it (one
    # thread is ~1.7x faster than two on the HS path), so use one when the scene has any
    python_plugins = any(type(v).__module__ == "mehs.render.plugins" for v in _objects(scene_dict))
    threads = dr.thread_count()
    if python_plugins:
        dr.set_thread_count(1)
    try:
        return _render_passes(mi, scene, s, progress)
    finally:
        dr.set_thread_count(threads)


def _objects(d: dict):
    for v in d.values():
        if isinstance(v, dict):
            yield from _objects(v)
        else:
            yield v


def _render_passes(mi, scene, s: RenderSettings, progress) -> np.ndarray:
    # render in equal passes so a long render shows progress; their mean is the same
    # estimator as one render with all the samples
    passes = render_passes(s.spp)
    acc = None
    for i, spp in enumerate(passes):
        img = np.array(mi.render(scene, spp=spp, seed=s.seed * 1009 + i), dtype=np.float64)
        acc = img if acc is None else acc + img
        if progress is not None:
            progress(spp)
    return (acc / len(passes)).astype(np.float32)


def render_spectral(s: RenderSettings, *, hs_map: EnvMap | None = None,
                    rgb_map: np.ndarray | None = None, progress=None) -> np.ndarray:
    """Spectral render ``(H, W, B)`` lit by ``hs_map`` (HSEnvmap) or ``rgb_map`` (Mitsuba's
    ``envmap``, Jakob–Hanika up-sampling). Exactly one of the two is given."""
    if (hs_map is None) == (rgb_map is None):
        raise ValueError("give exactly one of hs_map and rgb_map")
    mi = import_mitsuba()
    mi.set_variant(SPECTRAL_VARIANT)
    if hs_map is not None:
        from mehs.render.plugins import support_wavelengths

        lo, hi = s.bands[0] - s.band_width / 2, s.bands[-1] + s.band_width / 2
        sup = support_wavelengths(hs_map.wavelengths)
        if sup[0] > lo + 1e-6 or sup[-1] < hi - 1e-6:
            raise InputError(f"the map covers {hs_map.wavelengths[0]:g}–{hs_map.wavelengths[-1]:g}"
                             f" nm; the render needs {s.bands[0]:g}–{s.bands[-1]:g} nm",
                             hs_map.source or None)
        from mehs.render.plugins import plugin_classes

        HSEnvmap, _ = plugin_classes(SPECTRAL_VARIANT)
        emitter = HSEnvmap(mi.Properties(), envmap=hs_map)
    else:
        emitter = _rgb_envmap(mi, rgb_map)
    shape = _shape_dict(s.object)
    shape["bsdf"] = _bsdf(mi, s.material, spectral=True)
    scene = {"type": "scene", "integrator": {"type": "path", "max_depth": s.max_depth},
             "sensor": _camera(mi, dict(shape, bsdf={"type": "diffuse"}), s, _specfilm(s)),
             "object": shape, "light": emitter}
    # specfilm integrates radiance × response over λ: divide by the box width
    return _render(mi, scene, s, progress) / np.float32(s.band_width)


def render_rgb(s: RenderSettings, rgb_map: np.ndarray, progress=None) -> np.ndarray:
    """RGB render ``(H, W, 3)`` (linear sRGB) lit by Mitsuba's ``envmap`` with ``rgb_map``."""
    mi = import_mitsuba()
    mi.set_variant(RGB_VARIANT)
    shape = _shape_dict(s.object)
    shape["bsdf"] = _bsdf(mi, s.material, spectral=False)
    scene = {"type": "scene", "integrator": {"type": "path", "max_depth": s.max_depth},
             "sensor": _camera(mi, dict(shape, bsdf={"type": "diffuse"}), s, _rgbfilm(s)),
             "object": shape, "light": _rgb_envmap(mi, rgb_map)}
    return _render(mi, scene, s, progress)
