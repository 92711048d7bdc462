"""Spectral environment maps: reading mehs's HS maps and deriving the comparison maps.

An environment map here is a lat-long (equirectangular) image: row 0 is the zenith,
row ``H-1`` the nadir, columns sweep the azimuth once (Mitsuba's ``envmap``
convention, see :mod:`mehs.render.plugins`). Any ``H × W`` is accepted; ``W = 2H``
is the usual shape.

Sources (:func:`load_envmap`)
    - an ENVI cube (``.hdr``) or a spectral EXR (``S0.<λ>nm`` channels), read with
      :func:`mehs.io.load_cube`;
    - a per-wavelength EXR folder as :func:`mehs.export.export_per_wavelength`
      writes it (``<prefix>_wavelengths.json`` + one grayscale EXR per band).

    A dataset cube stores ``radiance × 2^-k`` (``mehs radiance scale`` in the ENVI
    header, ``mehsRadianceScale`` in an exported EXR's header, ``radiance_scale`` in the
    per-wavelength listing) so that its RGB pair fits half floats; the map is divided by
    that factor, so the emitter emits the cube's radiance, not 2^-k of it, and the factor
    is kept in ``metadata["radiance_scale"]``.

Derived maps (the paper's comparison, §4.4)
    :func:`rgb_map` — the pseudo-HDR-RGB of the HS map (:func:`mehs.rgb.hdr_rgb`,
    CIE 1931 2°, linear sRGB, negatives clipped); :func:`ssr_map` — that RGB map
    up-sampled back to spectra by an SSR model or the Smits 1999 baseline
    (:mod:`mehs.ssr.models`).
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from mehs.errors import FormatError, InputError
from mehs.export import parse_radiance_scale
from mehs.rgb import WAVELENGTHS_31, hdr_rgb, spectra_to_XYZ


@dataclass
class EnvMap:
    """A spectral lat-long environment map.

    Attributes
    ----------
    radiance
        float32 ``(H, W, B)``, finite and non-negative.
    wavelengths
        Band centres in nm, ``(B,)`` ascending.
    source
        Where it came from (file, folder or a description).
    """

    radiance: np.ndarray
    wavelengths: np.ndarray
    source: str = ""
    metadata: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        r = np.asarray(self.radiance, dtype=np.float32)
        # Mitsuba's envmap (the RGB renders) needs at least 2 columns and 3 rows
        if r.ndim != 3 or r.shape[0] < 3 or r.shape[1] < 2:
            raise InputError(f"an environment map must be (H ≥ 3, W ≥ 2, bands), got shape "
                             f"{r.shape}", self.source or None)
        wl = np.asarray(self.wavelengths, dtype=np.float64).reshape(-1)
        if wl.size != r.shape[2]:
            raise InputError(f"{wl.size} wavelengths for {r.shape[2]} bands", self.source or None)
        if wl.size < 2 or np.any(np.diff(wl) <= 0):
            raise InputError("map wavelengths must be ≥ 2 and strictly ascending",
                             self.source or None)
        if not np.isfinite(r).all():
            bad = int(np.count_nonzero(~np.isfinite(r)))
            raise InputError(f"the map holds {bad} NaN/Inf values", self.source or None)
        if (r < 0).any():
            raise InputError(f"the map holds negative radiance (min {float(r.min()):.4g}); "
                             "an emitter cannot emit negative light", self.source or None)
        self.radiance = np.ascontiguousarray(r)
        self.wavelengths = wl

    @property
    def shape(self) -> tuple[int, int]:
        return self.radiance.shape[:2]


def _read_per_wavelength_folder(folder: Path) -> EnvMap:
    from mehs.io.exr import read_exr

    listing = sorted(folder.glob("*_wavelengths.json"))
    if len(listing) != 1:
        raise InputError("a per-wavelength map folder must hold exactly one "
                         f"<prefix>_wavelengths.json (found {len(listing)})", folder)
    try:
        doc = json.loads(listing[0].read_text(encoding="utf-8"))
        files, wl = doc["files"], [float(w) for w in doc["wavelengths_nm"]]
    except (ValueError, KeyError, TypeError) as exc:
        raise FormatError(f"not a mehs per-wavelength listing ({exc})", listing[0]) from None
    if len(files) != len(wl) or not files:
        raise FormatError(f"{len(files)} files for {len(wl)} wavelengths", listing[0])
    _check_units(doc.get("units"), listing[0])
    scale = parse_radiance_scale(doc.get("radiance_scale"), listing[0])
    planes = []
    for name in files:
        p = folder / name
        if not p.is_file():
            raise InputError("band file listed in the wavelength list is missing", p)
        img = read_exr(p)
        if img.data.shape[2] != 1:
            raise FormatError(f"expected one channel per band file, got {img.channels}", p)
        if planes and img.data.shape[:2] != planes[0].shape:
            raise FormatError(f"band size {img.data.shape[:2]} differs from the first band's "
                              f"{planes[0].shape}", p)
        planes.append(img.data[:, :, 0])
    light, neg = _as_light(_unscaled(np.stack(planes, axis=-1), scale))
    return EnvMap(light, np.asarray(wl), str(folder),
                  {"units": doc.get("units"), "radiance_scale": scale, "negative_fraction": neg})


def _check_units(units, where) -> None:
    """Refuse cubes that hold no light: raw counts, or reflectance (a Specim IQ
    ``REFLECTANCE_*`` result, ``T.<λ>nm`` EXR channels), which is a ratio to a white
    reference and would light the scene with the camera's white instead of the sky."""
    u = str(units or "").strip().lower()
    if u == "dn":
        raise InputError("this cube holds raw counts (DN); fuse and resample it first "
                         "(mehs fuse, mehs resample) to get radiance", where)
    if "reflect" in u or "transmit" in u:
        raise InputError(f"this cube holds {u} (a ratio, not light); an environment map "
                         "must hold radiance (a fused HDR cube)", where)


def _unscaled(radiance: np.ndarray, scale: float | None) -> np.ndarray:
    # stored = radiance × scale (a power of two: dividing is exact)
    r = np.asarray(radiance, dtype=np.float32)
    return r if scale is None or scale == 1.0 else r / np.float32(scale)


def _as_light(radiance: np.ndarray) -> tuple[np.ndarray, float]:
    """Measured radiance as an emitter's light: negatives (the fused cube's unbiased noise
    around zero radiance) clipped to 0 here, where light must be non-negative, as the RGB
    step clips; returns the map and the fraction of samples clipped. NaN/Inf stay, for
    :class:`EnvMap` to refuse with the file named."""
    r = np.asarray(radiance, dtype=np.float32)
    neg = r < 0
    n = int(np.count_nonzero(neg))
    if n:
        r = np.where(neg, np.float32(0.0), r)
    return r, n / max(1, r.size)


def _exr_scale(path: Path) -> float | None:
    import OpenEXR

    try:
        header = OpenEXR.File(str(path), header_only=True).header()
    except (RuntimeError, ValueError, OSError) as exc:
        raise FormatError(f"cannot read the OpenEXR header ({exc})", path) from None
    return parse_radiance_scale(header.get("mehsRadianceScale"), path)


def load_envmap(path: str | Path) -> EnvMap:
    """Read an HS environment map (ENVI cube, spectral EXR or per-wavelength EXR folder).

    A dataset cube's stored radiance scale (2^-k) is divided out; the factor is kept in
    ``metadata["radiance_scale"]`` (None when the file has none).

    Raises
    ------
    InputError, FormatError
        Naming the file and the problem (missing band files, NaN, negative values, …).
    """
    p = Path(path)
    if not p.exists():
        raise InputError("environment map does not exist", p)
    if p.is_dir() and any(p.glob("*_wavelengths.json")):
        return _read_per_wavelength_folder(p)
    from mehs.io import load_cube

    cube = load_cube(p)
    _check_units(cube.units, p)
    # the EXR reader keeps no header in the cube's metadata: read the factor from the file
    scale = (_exr_scale(p) if p.suffix.lower() == ".exr"
             else parse_radiance_scale((cube.metadata or {}).get("mehs radiance scale"), p))
    light, neg = _as_light(_unscaled(cube.data, scale))
    return EnvMap(light, cube.wavelengths, str(p),
                  {"units": str(cube.units), "radiance_scale": scale, "negative_fraction": neg})


#: the CIE 1931 tables' range (nm): bands beyond it have no colour
CMF_RANGE_NM = (360.0, 830.0)


def _colorimetric_bands(envmap: EnvMap) -> tuple[np.ndarray, np.ndarray]:
    """Radiance ``(H, W, B')`` and wavelengths ``(B',)`` of the map's bands inside the CIE
    tables: a camera's NIR bands (a Specim IQ cube runs to 1004 nm) have no colour, and
    the colour tables refuse them."""
    wl = envmap.wavelengths
    sel = np.flatnonzero((wl >= CMF_RANGE_NM[0]) & (wl <= CMF_RANGE_NM[1]))
    if sel.size < 2:
        raise InputError(f"the map's bands ({wl[0]:g}–{wl[-1]:g} nm) leave fewer than 2 inside "
                         f"the visible {CMF_RANGE_NM[0]:g}–{CMF_RANGE_NM[1]:g} nm",
                         envmap.source or None)
    if sel.size == wl.size:
        return envmap.radiance, wl
    return envmap.radiance[..., sel[0]:sel[-1] + 1], wl[sel[0]:sel[-1] + 1]


def map_weights(envmap: EnvMap) -> np.ndarray:
    """Importance-sampling weights ``(H, W)`` of the sampling cells (luminance × sin θ).

    Cell ``(j, i)`` covers ``v ∈ [j/H, (j+1)/H]``, ``u ∈ [i/W, (i+1)/W]``; the bilinear
    look-up there reads pixels within one row/column of ``(j, i)``, so the weight is
    the largest luminance Y in that 3×3 neighbourhood (wrapping in u) times sin θ at the
    cell centre — never zero where the map emits. A floor of 1e-3 of the mean keeps
    pixels that emit only outside ȳ's support (deep violet) reachable.
    """
    from scipy.ndimage import maximum_filter

    h, w = envmap.shape
    y = spectra_to_XYZ(*_colorimetric_bands(envmap))[..., 1].astype(np.float64)
    y = np.clip(y, 0.0, None)
    emits = envmap.radiance.max(axis=-1) > 0
    mean = float(y.mean()) if y.size else 0.0
    y = y + np.where(emits, 1e-3 * mean if mean > 0 else 1.0, 0.0)
    y = maximum_filter(y, size=3, mode=("nearest", "wrap"))
    sin_t = np.sin((np.arange(h) + 0.5) / h * np.pi)[:, None]
    wts = y * sin_t
    if not (wts.sum() > 0):
        # an all-black map: sample uniformly (it contributes nothing anyway)
        wts = np.broadcast_to(sin_t, (h, w)).copy()
    return wts


def rgb_map(envmap: EnvMap) -> np.ndarray:
    """The pseudo-HDR linear-sRGB image ``(H, W, 3)`` float32 of an HS map (paper §3.1)."""
    return hdr_rgb(*_colorimetric_bands(envmap)).astype(np.float32)


def ssr_map(rgb: np.ndarray, model, name: str | None = None) -> EnvMap:
    """Up-sample an RGB map to spectra with an SSR model (``rgb (H, W, 3) → (H, W, B)``).

    Negative model outputs are clipped to 0 (an emitter cannot emit negative light);
    the clipped fraction is recorded in ``metadata["negative_fraction"]``.
    """
    out = np.asarray(model(np.asarray(rgb, dtype=np.float32)), dtype=np.float32)
    wl = np.asarray(getattr(model, "wavelengths", WAVELENGTHS_31), dtype=np.float64)
    neg = float(np.mean(out < 0)) if out.size else 0.0
    label = name or getattr(model, "name", "ssr")
    return EnvMap(np.clip(out, 0.0, None), wl, f"{label} up-sampling",
                  {"negative_fraction": neg, "model": label})


def uniform_map(spectrum: np.ndarray, wavelengths: np.ndarray, size: tuple[int, int] = (8, 16)
                ) -> EnvMap:
    """A constant map: every direction emits ``spectrum`` (B,) (tests, calibration)."""
    s = np.asarray(spectrum, dtype=np.float32).reshape(1, 1, -1)
    return EnvMap(np.broadcast_to(s, (*size, s.shape[-1])).copy(), wavelengths, "uniform map")
