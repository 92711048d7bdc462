"""Small paired HS/RGB sets from measured spectra, for tests, the demo and benchmarks.

Each scene is physically plausible and HDR:

- reflectances: the 24 ColorChecker patches (``colour.SDS_COLOURCHECKERS``,
  N Ohta) on a jittered grid, blended smoothly across patch borders (so the
  set holds mixtures, not just 24 spectra);
- light: two measured illuminants (``colour.SDS_ILLUMINANTS``: daylight,
  tungsten, fluorescent, LED, high-pressure sodium) mixed by a smooth field,
  times a smooth shading field spanning ``shading_stops`` stops;
- a directly visible light source (a disc of the first illuminant)
  ``source_gain`` times brighter than a white patch, which is what makes the
  pseudo-RGB need HDR;
- a few pixels marked invalid in the mask (bit 2, "ghost") whose ground truth
  is deliberately zero, so an evaluation that ignores the mask is caught.

Files follow the dataset folder format 3 (``manifest.json``, ``index.csv``,
``scenes/<id>/{hs.hdr,hs.dat,hdr_rgb.exr,ldr_rgb.png,mask.png}``) and are
written with the toolkit's writers (ENVI, OpenEXR, atomic PNG).
"""

from __future__ import annotations

from pathlib import Path
from typing import Sequence

import numpy as np

from mehs.rgb import WAVELENGTHS_31, spectra_to_linear_sRGB

#: Broadband illuminants by default; spiky ones (HP1, LED-V1, FL11) can be asked for.
ILLUMINANTS = ("D65", "D50", "D75", "A", "FL2", "LED-B3")


def _spectra(names_or_sds, wl: np.ndarray) -> np.ndarray:
    return np.stack([np.interp(wl, sd.wavelengths, sd.values) for sd in names_or_sds])


def _smooth_field(rng: np.random.Generator, h: int, w: int, n_waves: int = 3) -> np.ndarray:
    """A smooth random field in [0, 1], shape ``(h, w)``."""
    yy, xx = np.mgrid[0:h, 0:w]
    yy = yy / max(h - 1, 1)
    xx = xx / max(w - 1, 1)
    f = np.zeros((h, w))
    for _ in range(n_waves):
        fx, fy = rng.uniform(0.3, 1.5, 2)
        ph = rng.uniform(0, 2 * np.pi)
        f += np.sin(2 * np.pi * (fx * xx + fy * yy) + ph)
    f -= f.min()
    return f / max(f.max(), 1e-12)


def make_scene_spectra(size: int | tuple[int, int] = 64, seed: int = 0, *,
                       wavelengths: np.ndarray = WAVELENGTHS_31, shading_stops: float = 6.0,
                       source_gain: float = 1000.0, n_invalid: int = 5,
                       illuminants: Sequence[str] = ILLUMINANTS,
                       ) -> tuple[np.ndarray, np.ndarray, dict]:
    """One synthetic HDR scene.

    Returns
    -------
    spectra
        float32 ``(H, W, B)`` relative radiance (white patch under the mean light ≈ 1).
    mask
        uint8 ``(H, W)``: 0 valid, 2 for the pixels made invalid on purpose.
    info
        ``{"illuminants": [...], "source_gain": ..., "shading_stops": ...}``.
    """
    import colour

    h, w = (size, size) if np.isscalar(size) else tuple(int(s) for s in size)
    rng = np.random.default_rng(seed)
    wl = np.asarray(wavelengths, dtype=np.float64)
    refl = _spectra(list(colour.SDS_COLOURCHECKERS["ColorChecker N Ohta"].values()), wl)
    ill_names = [str(n) for n in rng.choice(list(illuminants), size=2, replace=len(illuminants) < 2)]
    ills = _spectra([colour.SDS_ILLUMINANTS[n] for n in ill_names], wl)
    # Each illuminant scaled so a perfect white under it has Y = 1.
    from mehs.rgb import spectra_to_XYZ
    ills /= spectra_to_XYZ(ills, wl)[:, 1:2]

    # Patch layout: a jittered grid of 4×4 centres with soft assignment.
    g = 4
    cy, cx = np.meshgrid((np.arange(g) + 0.5) / g, (np.arange(g) + 0.5) / g, indexing="ij")
    centres = np.stack([cy.ravel(), cx.ravel()], 1) + rng.normal(0, 0.04, (g * g, 2))
    patch = rng.choice(len(refl), size=g * g, replace=False)
    yy, xx = np.mgrid[0:h, 0:w]
    pos = np.stack([yy / max(h - 1, 1), xx / max(w - 1, 1)], -1)
    d2 = ((pos[:, :, None, :] - centres[None, None]) ** 2).sum(-1)
    logits = -d2 / (2 * (0.35 / g) ** 2)
    logits -= logits.max(-1, keepdims=True)
    wts = np.exp(logits)
    wts /= wts.sum(-1, keepdims=True)
    R = wts @ refl[patch]                                       # (h, w, B)

    mix = _smooth_field(rng, h, w)[..., None]
    light = mix * ills[0] + (1 - mix) * ills[1]                 # (h, w, B)
    shade = 2.0 ** (shading_stops * (_smooth_field(rng, h, w) - 0.5))
    spectra = R * light * shade[..., None]

    # A directly visible light source: emission only, very bright.
    r0, c0 = rng.uniform(0.15, 0.85, 2) * (h, w)
    rad = max(1.5, 0.06 * min(h, w))
    disc = (yy - r0) ** 2 + (xx - c0) ** 2 <= rad ** 2
    spectra[disc] = ills[0] * source_gain

    mask = np.zeros((h, w), dtype=np.uint8)
    if n_invalid:
        flat = rng.choice(h * w, size=min(n_invalid, h * w), replace=False)
        mask.reshape(-1)[flat] = 2
        spectra.reshape(-1, wl.size)[flat] = 0.0
    info = {"illuminants": ill_names, "source_gain": source_gain,
            "shading_stops": shading_stops}
    return spectra.astype(np.float32), mask, info


def _natural_spectra(size, seed: int, pool: str, source_gain: float, n_invalid: int = 5):
    """A natural scene at 400:700:10 from ``pool``; the same invalid-pixel trap as above."""
    from mehs.scenes.natural import make_natural_scene

    h, w = (size, size) if np.isscalar(size) else tuple(int(s) for s in size)
    scene = make_natural_scene(h, w, wavelengths=WAVELENGTHS_31, seed=seed, pool=pool,
                               source_ratio=source_gain)
    spectra = scene.radiance
    mask = np.zeros((h, w), dtype=np.uint8)
    flat = np.random.default_rng(seed).choice(h * w, size=min(n_invalid, h * w), replace=False)
    mask.reshape(-1)[flat] = 2
    spectra.reshape(-1, WAVELENGTHS_31.size)[flat] = 0.0
    info = {k: scene.info[k] for k in ("generator", "pool", "lighting", "lights", "source_ratio",
                                       "n_materials")}
    return spectra, mask, info


def _write_png(path: Path, img: np.ndarray) -> Path:
    import cv2

    from mehs.errors import FormatError
    from mehs.io.atomic import atomic_path

    if img.ndim == 3:
        img = np.ascontiguousarray(img[..., ::-1])
    with atomic_path(path) as tmp:
        if not cv2.imwrite(str(tmp), img):
            raise FormatError("OpenCV could not write the PNG", path)
    return path


def make_paired_set(out_dir: str | Path, n_scenes: int = 10, size: int | tuple[int, int] = 64,
                    seed: int = 0, *, splits: Sequence[float] = (0.6, 0.2, 0.2),
                    shading_stops: float = 6.0, source_gain: float = 1000.0,
                    illuminants: Sequence[str] = ILLUMINANTS,
                    generator: str = "colorchecker", pool: str | None = None) -> Path:
    """Write a small ME HS-style dataset (format 3) of ``n_scenes`` synthetic scenes.

    Scenes are assigned to train/val/test in the ratio ``splits`` (at least one
    test scene). Deterministic for a given ``seed``. Returns ``out_dir``.

    ``generator``: ``"colorchecker"`` (:func:`make_scene_spectra`) or ``"natural"``
    (:func:`mehs.scenes.natural.make_natural_scene`, each scene drawn from the material and
    light pool of its split, so the test scenes hold materials and lights never trained on;
    ``source_gain`` is the visible source's ratio, ``shading_stops``/``illuminants`` unused).
    ``pool`` overrides the split's pool for every scene (``"all"``: no held-out materials).
    """
    if generator not in ("colorchecker", "natural"):
        raise ValueError(f"generator must be 'colorchecker' or 'natural', got {generator!r}")
    from mehs import __version__
    from mehs.cube import SpectralCube
    from mehs.io.atomic import write_json_atomic
    from mehs.io.envi import write_envi
    from mehs.io.exr import write_exr_rgb
    from mehs.rgb import ldr_rgb
    from mehs.ssr.data import DATASET_FORMAT, write_index_csv

    out = Path(out_dir)
    (out / "scenes").mkdir(parents=True, exist_ok=True)
    n = int(n_scenes)
    ids = [f"syn{seed:03d}_{i:03d}" for i in range(n)]
    frac = np.asarray(splits, dtype=float)
    if frac.shape != (3,) or not np.all(np.isfinite(frac)) or np.any(frac < 0) \
            or frac.sum() <= 0:
        raise ValueError(f"splits must be three non-negative train/val/test ratios, not all "
                         f"zero, got {tuple(splits)}")
    frac = frac / frac.sum()
    n_test = min(n, max(1, int(round(frac[2] * n)))) if n > 1 else 0
    # rounded val and test may together exceed n (e.g. 0, 0.5, 0.5 of 3 scenes): the val
    # count gives way, so n_train is never negative and no scene lands in two splits
    n_val = min(int(round(frac[1] * n)), n - n_test) if n > 2 else 0
    n_train = n - n_test - n_val
    split_ids = {"train": ids[:n_train], "val": ids[n_train:n_train + n_val],
                 "test": ids[n_train + n_val:]}
    scenes, rows = [], []
    for i, sid in enumerate(ids):
        split = next(k for k, v in split_ids.items() if sid in v)
        if generator == "natural":
            spectra, mask, info = _natural_spectra(size, seed * 100_003 + i, pool or split,
                                                   source_gain)
        else:
            spectra, mask, info = make_scene_spectra(size, seed * 100_003 + i,
                                                     shading_stops=shading_stops,
                                                     source_gain=source_gain,
                                                     illuminants=illuminants)
        d = out / "scenes" / sid
        d.mkdir(parents=True, exist_ok=True)
        cube = SpectralCube(spectra, WAVELENGTHS_31, units="relative radiance",
                            source=None, metadata={"description": f"mehs synthetic scene {sid}"})
        write_envi(d / "hs.hdr", cube, dtype=np.float32, interleave="bil", data_ext=".dat")
        hdr = spectra_to_linear_sRGB(spectra, WAVELENGTHS_31).astype(np.float32)
        write_exr_rgb(d / "hdr_rgb.exr", hdr, half=True)
        ldr, exposure = ldr_rgb(hdr)
        _write_png(d / "ldr_rgb.png", np.asarray(ldr, dtype=np.uint8))
        _write_png(d / "mask.png", mask)
        files = {"hs": f"scenes/{sid}/hs.hdr", "hs_data": f"scenes/{sid}/hs.dat",
                 "hdr_rgb": f"scenes/{sid}/hdr_rgb.exr",
                 "ldr_rgb": f"scenes/{sid}/ldr_rgb.png", "mask": f"scenes/{sid}/mask.png"}
        scenes.append({"id": sid, "status": "pass", "reasons": [], "files": files,
                       "sha256": {},
                       "quality": {"invalid_fraction": float(np.mean(mask != 0)),
                                   "ldr_exposure": float(exposure)},
                       "provenance": {"generator": "mehs.ssr.synthetic", "seed": seed,
                                      **info}})
        rows.append({"id": sid, "status": "pass", "split": split, **{k: files[k] for k in
                     ("hs", "hdr_rgb", "ldr_rgb", "mask")}})
    manifest = {"format": DATASET_FORMAT, "software_version": __version__,
                "wavelengths": WAVELENGTHS_31.tolist(),
                "rgb": {"xyz_scale": "1/sum(ybar)",
                        "ldr_exposure_rule": "mehs.rgb.ldr_rgb default (recorded per scene "
                                             "as quality.ldr_exposure)"},
                "scenes": scenes, "splits": split_ids}
    write_index_csv(out / "index.csv", rows)
    write_json_atomic(out / "manifest.json", manifest)
    return out
