"""Natural HDR scenes from measured reflectances and lights (``make_natural_scene``).

A scene is a dead-leaves layout (:mod:`mehs.scenes.layout`) whose regions are materials drawn
from one pool of measured reflectances (:mod:`mehs.scenes.library`), lit by a lighting setting
drawn from the same pool of lights:

==============  ===========================================  ==================================
setting         direct light (shading, cast shadows)          fill light / visible source
==============  ===========================================  ==================================
``daylight``    sun: CIE D series, 4000–7000 K               sky: D series 7500–20000 K in the
                                                             shadows; the sky and the sun's glare
``tungsten``    Planck 2200–3400 K or a measured lamp        the same light, indirect; the bulb
``fluorescent`` F series / measured tubes                    the same light, indirect; the tube
``led``         CIE LED series / measured LEDs               the same light, indirect; the LED
``sodium``      high-pressure sodium (night street)          dim sky; the street lamp
``mixed``       indoor tungsten / fluorescent / LED           daylight from a window, falling off
                                                             across the room; the window
==============  ===========================================  ==================================

Radiance per pixel (neutral interface reflection: highlights carry the light's spectrum,
Lee 1986 / Shafer 1985 dichromatic model)::

    L = R ⊙ (k_d·(1 − shadow)·cos·E_direct + k_f·E_fill + Σ_j b_j·E_j) · texture + k_s·spec·E_direct

where the ``E_j`` are two local lamps of other families (a desk lamp, a shop window, an LED
street light beside a sodium one; falling off around a point) and the light bounced off the
four largest surfaces, ``R_k ⊙ E_direct`` (interreflection); ``R`` is the region's
reflectance (a measured sample, or a subtractive mixture of two of the pool's samples,
``R_a^(1−t)·R_b^t``) blended per pixel with a second pool material by a 1/f noise field
(lichen on stone, grain in wood), times a multiplicative fine texture. A visible
light source (a lamp core with a 1/r³ glow, or a window / the sky) reaches
``source_ratio`` × the diffuse white — up to 10⁴ (HDR).

Units: relative radiance; each light is normalised to mean 1 over 400–700 nm, so a white
diffuse surface facing the direct light has radiance ≈ 1 (as :mod:`mehs.capture.scene`).

References
----------
- Shafer (1985), "Using color to separate reflection components", Color Res. Appl. 10(4).
- Lee (1986), "Method for computing the scene-illuminant chromaticity from specular
  highlights", JOSA A 3(10) (neutral interface reflection).
- Lee, Mumford & Huang (2001), dead-leaves occlusion model, IJCV 41.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from mehs.capture.scene import SPECIM_IQ_FWHM, SPECIM_IQ_WAVELENGTHS, Scene, band_fwhm, check_wavelengths
from mehs.errors import InputError
from mehs.scenes.layout import make_layout, noise_field
from mehs.scenes.library import (Light, check_pool, draw_light, light_spectrum, material_library,
                                 material_pools)

#: Lighting settings of :func:`make_natural_scene`.
LIGHTINGS = ("daylight", "tungsten", "fluorescent", "led", "sodium", "mixed")

_INDOOR = ("tungsten", "fluorescent", "led")
# families of the second, local lamp of each setting
_SECOND = {"daylight": ("tungsten", "fluorescent", "led"), "tungsten": ("fluorescent", "led"),
           "fluorescent": ("tungsten", "led"), "led": ("tungsten", "fluorescent"),
           "sodium": ("led", "discharge", "fluorescent"), "mixed": ("tungsten", "fluorescent", "led")}


def _lights(setting: str, pool: str, rng: np.random.Generator) -> tuple[Light, Light, float]:
    """``(direct, fill, fill level)`` of a lighting setting."""
    if setting == "daylight":
        return draw_light("sun", pool, rng), draw_light("sky", pool, rng), float(rng.uniform(0.1, 0.3))
    if setting in _INDOOR:
        direct = draw_light(setting, pool, rng)
        return direct, direct, float(rng.uniform(0.08, 0.25))
    if setting == "sodium":
        return draw_light("sodium", pool, rng), draw_light("sky", pool, rng), float(rng.uniform(0.01, 0.05))
    if setting == "mixed":
        indoor = draw_light(_INDOOR[int(rng.integers(3))], pool, rng)
        return indoor, draw_light("sun", pool, rng), float(rng.uniform(0.4, 1.2))
    raise InputError(f"unknown lighting {setting!r}; use one of {', '.join(LIGHTINGS)}")


def _region_materials(rng: np.random.Generator, table: np.ndarray, pool_idx: np.ndarray,
                      n_regions: int, mix_fraction: float):
    """Per-region base and secondary reflectances and the measured samples they came from."""
    a = rng.choice(pool_idx, size=n_regions)
    b = rng.choice(pool_idx, size=n_regions)
    c = rng.choice(pool_idx, size=n_regions)
    # a subtractive (Beer–Lambert) mixture of two pool samples: a dyed / weathered variant
    t = np.where(rng.uniform(size=n_regions) < mix_fraction, rng.uniform(0.15, 0.85, n_regions), 0.0)
    eps = 1e-4
    base = np.exp((1 - t)[:, None] * np.log(table[a] + eps) + t[:, None] * np.log(table[b] + eps)) - eps
    return np.clip(base, 0.0, 1.0), table[c], a, b, t, c


def make_natural_scene(lines: int = 256, samples: int | None = None,
                       wavelengths: np.ndarray | None = None, *, seed: int = 0,
                       pool: str = "all", lighting: str | None = None,
                       source_ratio: float | None = None, motion: bool = False,
                       density: float = 1.0, fwhm: np.ndarray | None = None) -> Scene:
    """A natural HDR scene (see the module notes).

    Parameters
    ----------
    lines, samples
        Spatial size (``samples`` defaults to ``lines``).
    wavelengths
        Band centres (nm); default the 204 Specim IQ bands.
    seed
        Everything random (layout, materials, lights, texture) follows from it.
    pool
        ``"train"``, ``"val"``, ``"test"`` (disjoint materials and lights) or ``"all"``.
    lighting
        One of :data:`LIGHTINGS`; default drawn from the seed.
    source_ratio
        Radiance of the visible light source relative to the diffuse white (≤ 0: none);
        default log-uniform in 100–10⁴.
    motion
        Add a bright object that drifts between exposures (ghost tests).
    density
        Shapes per 100 pixels of area (more = smaller regions, more materials).

    Returns
    -------
    Scene
        float32 radiance ``(lines, samples, bands)``; ``info`` records the lights (family,
        name, kelvin), the pool, and ``materials``: the measured samples visible in the scene
        as ``"set/name"``, with ``n_materials`` (distinct region materials, mixtures included).
    """
    samples = lines if samples is None else samples
    if lines < 8 or samples < 8:
        raise InputError(f"a natural scene needs at least 8×8 pixels, got {lines}×{samples}")
    check_pool(pool)
    if source_ratio is not None and not np.isfinite(source_ratio):  # before seconds of work
        raise InputError(f"source_ratio must be finite, got {source_ratio}")
    if not density > 0:
        raise InputError(f"density must be > 0, got {density}")
    wl = SPECIM_IQ_WAVELENGTHS.copy() if wavelengths is None else check_wavelengths(wavelengths)
    if fwhm is None:
        fwhm = SPECIM_IQ_FWHM.copy() if wavelengths is None else np.full(wl.size, 7.0)
    fwhm = band_fwhm(fwhm, wl)
    rng = np.random.default_rng(seed)
    setting = lighting or LIGHTINGS[int(rng.integers(len(LIGHTINGS)))]
    direct, fill, fill_level = _lights(setting, pool, rng)
    e_dir, e_fill = light_spectrum(direct, wl, fwhm), light_spectrum(fill, wl, fwhm)

    # the direct light comes from above, to one side; low sun = long shadows
    elev = rng.uniform(0.3, 1.1)
    az = rng.uniform(-np.pi * 0.9, -np.pi * 0.1)
    light_dir = (float(np.cos(elev) * np.cos(az)), float(np.cos(elev) * np.sin(az)), float(np.sin(elev)))
    lay = make_layout(rng, lines, samples, light_dir=light_dir,
                      shadow_length=0.6 if setting in ("daylight", "sodium") else 0.25, density=density)

    names, table = material_library(wl)
    pool_idx = material_pools(wl)[pool]
    base, second, ia, ib, t, ic = _region_materials(rng, table, pool_idx, lay.n_regions, 0.5)
    # per region: how much of the second material shows through, and how rough the texture is
    blend_gain = np.where(rng.uniform(size=lay.n_regions) < 0.6, rng.uniform(0.2, 0.8, lay.n_regions), 0.0)
    # half the blends are subtractive (a stain, wetness, a varying dye load: Beer–Lambert in
    # the concentration), half linear (sub-pixel mosaics of two surfaces: lichen on stone)
    subtractive = (rng.uniform(size=lay.n_regions) < 0.5).astype(np.float32)
    blend_bias = rng.uniform(-1.5, 0.0, lay.n_regions)
    tex_gain = rng.uniform(0.02, 0.25, lay.n_regions)
    fields = np.stack([noise_field(rng, (lines, samples), beta) for beta in (1.4, 1.8, 2.2)])
    field_of = rng.integers(0, 3, lay.n_regions)

    lab = lay.label
    f_pix = fields[field_of[lab], np.arange(lines)[:, None], np.arange(samples)[None, :]]
    w_mix = np.clip(blend_gain[lab] * (f_pix - blend_bias[lab]) * 0.5, 0.0, 1.0).astype(np.float32)
    f2 = fields[(field_of[lab] + 1) % 3, np.arange(lines)[:, None], np.arange(samples)[None, :]]
    texture = np.clip(1.0 + tex_gain[lab] * f2, 0.3, 2.0).astype(np.float32)
    direct_w = (lay.lambert * (1.0 - lay.shadow)).astype(np.float32)
    fill_w = np.full((lines, samples), fill_level, dtype=np.float32)
    if setting == "mixed":
        # window light enters from one side and falls off across the room
        u = np.linspace(0, 1, samples, dtype=np.float32)[None, :]
        side = u if rng.uniform() < 0.5 else 1 - u
        fill_w = (fill_level * (0.05 + 0.95 * side ** 2) * (0.6 + 0.4 * lay.lambert)).astype(np.float32)
    extra_w, extra_spd = _interreflections(lab, base, e_dir, rng)
    # local lamps lighting parts of the scene (a shop window, a desk lamp, an LED street
    # light beside the sodium one): real scenes are rarely lit by one spectrum
    yy, xx = np.mgrid[0:lines, 0:samples].astype(np.float32)
    d0 = 0.15 * min(lines, samples)
    locals_ = []
    for fam in rng.permutation(_SECOND[setting])[:2]:
        lamp = draw_light(str(fam), pool, rng)
        py, px = rng.uniform(0, 1) * lines, rng.uniform(0, 1) * samples
        # in sunlight an artificial lamp only shows in the shade
        level = float(rng.uniform(0.05, 0.2) if setting == "daylight" else rng.uniform(0.4, 1.2))
        extra_w.append((level * (0.3 + 0.7 * lay.lambert) /
                         (1 + ((yy - py) ** 2 + (xx - px) ** 2) / d0 ** 2) ** 1.5).astype(np.float32))
        extra_spd.append(light_spectrum(lamp, wl, fwhm).astype(np.float32))
        locals_.append({"role": "local", "family": lamp.family, "name": lamp.name,
                        "kelvin": lamp.kelvin, "level": level})
    del yy, xx
    radiance = np.empty((lines, samples, wl.size), dtype=np.float32)
    base32, second32 = base.astype(np.float32), second.astype(np.float32)
    logb32, logs32 = np.log(base32 + 1e-4), np.log(second32 + 1e-4)
    ed32, ef32 = e_dir.astype(np.float32), e_fill.astype(np.float32)
    step = max(1, (1 << 21) // max(1, samples * wl.size))
    for r0 in range(0, lines, step):  # row blocks bound the (H, W, B) temporaries
        sl = slice(r0, r0 + step)
        lb, wm = lab[sl], w_mix[sl][..., None]
        sub = subtractive[lb][..., None]
        lin = base32[lb] * (1 - wm) + second32[lb] * wm
        dye = np.exp((1 - wm) * logb32[lb] + wm * logs32[lb]) - 1e-4
        refl = lin + sub * (dye - lin)
        light = direct_w[sl][..., None] * ed32 + fill_w[sl][..., None] * ef32
        for ew, es in zip(extra_w, extra_spd):
            light += ew[sl][..., None] * es
        radiance[sl] = refl * light * texture[sl][..., None] + lay.specular[sl][..., None] * ed32
    info: dict[str, Any] = {
        "kind": "natural", "generator": "mehs.scenes.natural", "seed": int(seed), "pool": pool,
        "lighting": setting, "illuminant": direct.label, "fill_light": fill.label,
        "lights": [{"role": "direct", "family": direct.family, "name": direct.name,
                    "kelvin": direct.kelvin},
                   {"role": "fill", "family": fill.family, "name": fill.name, "kelvin": fill.kelvin,
                    "level": fill_level}] + locals_,
    }
    visible = np.unique(lab)
    used = set(ia[visible].tolist()) | set(ib[visible][t[visible] > 0].tolist()) | \
        set(ic[visible][blend_gain[visible] > 0].tolist())
    info["materials"] = sorted(f"{names[i][0]}/{names[i][1]}" for i in used)
    keys = {(int(ia[k]), int(ib[k]) if t[k] > 0 else -1, round(float(t[k]), 3)) for k in visible}
    info["n_materials"] = len(keys)
    info["n_measured_materials"] = len(used)
    ratio = float(np.exp(rng.uniform(np.log(100), np.log(1e4)))) if source_ratio is None else float(source_ratio)
    _add_sources(radiance, setting, ratio, e_dir, e_fill, rng, info)
    info["source_ratio"] = ratio
    # the white reference tile lies in the open, facing the direct light
    white = (0.99 * (e_dir + fill_level * e_fill)).astype(np.float32)
    scene = Scene(name="natural", radiance=radiance, wavelengths=wl,
                  fwhm=np.asarray(fwhm, np.float64), moving=bool(motion), white_radiance=white,
                  info=info)
    if motion:
        _add_motion(scene, e_dir, rng)
    return scene


def _interreflections(label: np.ndarray, base: np.ndarray, e_dir: np.ndarray,
                      rng: np.random.Generator, n: int = 4):
    """Light bounced off the largest regions onto their surroundings (mutual illumination).

    Each of the ``n`` largest visible regions re-emits ``R ⊙ E_direct``, falling off with
    distance from it (a Gaussian of its mask, 10 % of the frame wide); returns the weight
    fields ``(lines, samples)`` and the bounced spectra ``(bands,)``, float32.
    """
    from scipy.ndimage import gaussian_filter

    counts = np.bincount(label.ravel(), minlength=base.shape[0])
    big = np.argsort(-counts)[:n]
    sigma = 0.1 * min(label.shape)
    weights, spds = [], []
    for k in big:
        if counts[k] == 0:
            continue
        f = gaussian_filter((label == k).astype(np.float32), sigma, mode="nearest")
        f *= float(rng.uniform(0.1, 0.35)) / max(float(f.max()), 1e-6)
        weights.append(f.astype(np.float32))
        spds.append((base[k] * e_dir).astype(np.float32))
    return weights, spds


def _glow_disc(radiance: np.ndarray, cy: float, cx: float, rad: float, spd: np.ndarray,
               ratio: float) -> int:
    """A lamp core of ``ratio`` × ``spd`` with a 1/r³ glare halo (0.5 % at the rim); returns pixels."""
    lines, samples = radiance.shape[:2]
    yy, xx = np.mgrid[0:lines, 0:samples].astype(np.float32)
    r = np.sqrt((yy - cy) ** 2 + (xx - cx) ** 2)
    core = r <= rad
    glow = np.where(core, 0.0, 0.005 * ratio * (rad / np.maximum(r, rad)) ** 3).astype(np.float32)
    radiance += glow[..., None] * spd.astype(np.float32)
    radiance[core] = (spd * ratio).astype(np.float32)
    return int(core.sum())


def _add_sources(radiance: np.ndarray, setting: str, ratio: float, e_dir: np.ndarray,
                 e_fill: np.ndarray, rng: np.random.Generator, info: dict) -> None:
    """Directly visible light: lamp / sun with glare, the sky, a window."""
    lines, samples = radiance.shape[:2]
    size = min(lines, samples)
    if setting == "daylight":
        # a band of sky at the top: bluer fill light, brighter towards the horizon
        h = int(rng.uniform(0.08, 0.22) * lines)
        if h > 0:
            grad = np.linspace(2.0, 6.0, h, dtype=np.float32)[:, None, None]
            radiance[:h] = grad * e_fill.astype(np.float32)
            info["sky_lines"] = h
    if ratio <= 0:
        return
    if setting == "mixed":
        y0, x0 = int(rng.uniform(0.05, 0.3) * lines), int(rng.uniform(0.05, 0.75) * samples)
        win = (slice(y0, y0 + max(2, int(0.2 * lines))), slice(x0, x0 + max(2, int(0.18 * samples))))
        # a window: daylight seen directly, ``ratio`` / 10 (a sunlit scene outside, not the sun)
        radiance[win] = (e_fill * max(ratio / 10.0, 5.0)).astype(np.float32)
        info["source"] = "window"
        info["source_pixels"] = int(radiance[win].shape[0] * radiance[win].shape[1])
        return
    spd = e_dir
    cy, cx = rng.uniform(0.05, 0.35) * (lines - 1), rng.uniform(0.1, 0.9) * (samples - 1)
    if setting == "fluorescent":
        # a tube: a bright bar
        y0, x0 = int(cy), int(max(0, cx - 0.2 * samples))
        # at least one auto-exposure probe line apart (16 probe lines): a source the probes
        # miss saturates in every exposure
        thick = max(2, int(np.ceil(lines / 16)) + 1, int(0.025 * lines))
        bar = (slice(y0, y0 + thick), slice(x0, x0 + max(3, int(0.4 * samples))))
        radiance[bar] = (spd * ratio).astype(np.float32)
        info["source"] = "tube"
        info["source_pixels"] = int(radiance[bar].shape[0] * radiance[bar].shape[1])
        return
    rad = max(1.5, 0.035 * size, (lines / 16 + 2) / 2)
    info["source"] = {"daylight": "sun", "sodium": "street lamp"}.get(setting, "lamp")
    info["source_pixels"] = _glow_disc(radiance, cy, cx, rad, spd, ratio)


def _add_motion(scene: Scene, e_dir: np.ndarray, rng: np.random.Generator) -> None:
    """A bright drifting object (cloud / water glint), as :func:`mehs.capture.scene.make_scene`."""
    lines, samples = scene.radiance.shape[:2]
    scene._blob_spectrum = (3.0 * e_dir).astype(np.float32)
    scene._blob_center = (float(rng.uniform(0.5, 0.8)) * (lines - 1), 0.25 * (samples - 1))
    scene._blob_radius = max(2.0, 0.12 * min(lines, samples))
    scene.motion_step = max(1.0, 0.06 * samples)
    scene.radiance += scene._blob(0)[..., None] * scene._blob_spectrum[None, None, :]
    scene.info["motion_step"] = scene.motion_step
