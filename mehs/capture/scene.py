"""Simulated scenes: spectral radiance built from measured spectra.

A :class:`Scene` is a relative spectral radiance cube ``(lines, samples, bands)``
made of ColorChecker reflectances (``colour.SDS_COLOURCHECKERS``) lit by a CIE
illuminant (``colour.SDS_ILLUMINANTS``), with smooth shading, a mild texture and
sharp patch edges, plus a directly visible light source 100–10 000× brighter
than the diffuse white — the part that makes the scene high dynamic range.

Units
-----
Relative radiance: the illuminant is normalised so that its mean over
400–700 nm is 1, hence a perfect diffuse white at full shading has radiance
≈ 1 in the visible. A light source with ``source_ratio=1000`` has a mean
visible radiance of 1000.

Spectra outside the tables
--------------------------
colour-science tabulates reflectances to 730/780 nm and illuminants to
780 nm, while the Specim IQ grid reaches 1004 nm. Reflectances are extended
with their last tabulated value (no measured data; see the limits below).
Lights continue as :mod:`mehs.scenes.lights` says: illuminant A by its CIE
formula, the D illuminants as the CIE D series (tabulated to 830 nm),
tungsten lamps by Planck's law, the others with the mean of their last 20 nm
(which keeps a discharge lamp's continuum, not its last line). Nothing is ever
extrapolated to negative values.

The flat reflectance beyond 780 nm is a stand-in, not a measurement: most
organic pigments of a real chart turn transparent in the near infrared and
its patches rise there (all but the carbon-black ones).

Band values
-----------
A band of the camera sees its spectral response function (a Gaussian of the
scene's ``fwhm``), not the spectrum at its centre. Lights are therefore
averaged over each band's Gaussian (±5σ, :data:`~mehs.calibration.spectra.GAUSS_SUPPORT_SIGMA`), as a calibration against the same
tabulated SPD does (:func:`mehs.calibration.spectra.band_average`): a
discharge or fluorescent line narrower than a band would otherwise be 30–60 %
off in the bands around it. Reflectances are smooth at this scale (point
sampling and a 7 nm band average differ by < 0.3 % at the 99th percentile) and
are sampled at the band centres.

References
----------
- McCamy, Marcus & Davidson (1976), "A color-rendition chart", J. Appl. Photogr. Eng. 2(3).
- CIE 015:2018 Colorimetry (illuminants A, D65, F, HP, LED series as tabulated by colour-science).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import lru_cache
from typing import Any

import numpy as np

from mehs.calibration.spectra import GAUSS_SUPPORT_SIGMA
from mehs.errors import InputError
from mehs.scenes.lights import light_function, planck  # noqa: F401 - planck is public here


def _specim_iq_grid() -> np.ndarray:
    # A quadratic dispersion through the documented Specim IQ band centres:
    # band 1 = 397.32, 19 = 449.4, 53 = 548.6, 70 = 598.6, 204 = 1003.58 nm
    # (1-based), with both end points held exactly.
    idx = np.array([0, 18, 52, 69, 203], dtype=np.float64)
    wl = np.array([397.32, 449.4, 548.6, 598.6, 1003.58])
    # Parameterise λ(i) = a + b i + c i² with the two ends fixed; fit c by least squares.
    n = 203.0
    base = wl[0] + (wl[-1] - wl[0]) * idx / n
    curv = idx * (idx - n)
    c = float(np.dot(curv[1:-1], (wl - base)[1:-1]) / np.dot(curv[1:-1], curv[1:-1]))
    i = np.arange(204, dtype=np.float64)
    out = wl[0] + (wl[-1] - wl[0]) * i / n + c * i * (i - n)
    out[0], out[-1] = 397.32, 1003.58
    return np.round(out, 2)


#: The 204 Specim IQ band centres (nm), 397.32 … 1003.58, 2.9–3.1 nm apart, 103 in 400–700.
SPECIM_IQ_WAVELENGTHS: np.ndarray = _specim_iq_grid()
SPECIM_IQ_WAVELENGTHS.setflags(write=False)

#: Specim IQ band width (nm): the published spectral resolution is 7 nm FWHM.
SPECIM_IQ_FWHM: np.ndarray = np.full(204, 7.0)
SPECIM_IQ_FWHM.setflags(write=False)

#: Scene kinds accepted by :func:`make_scene`.
SCENE_KINDS = ("colorchecker", "lamp", "window", "ramp")

_CHECKER = "ColorChecker N Ohta"


def srf_average(fn, wavelengths: np.ndarray, fwhm: np.ndarray | float | None) -> np.ndarray:
    """Mean of the spectrum ``fn(λ)`` over Gaussian bands of ``wavelengths`` and ``fwhm`` (nm).

    ``fwhm=None`` (or 0) samples ``fn`` at the centres. ``fn`` maps an array of
    wavelengths (any shape) to values of the same shape. Shape ``(bands,)`` float64.
    """
    wl = np.asarray(wavelengths, dtype=np.float64).reshape(-1)
    if fwhm is None:
        return np.asarray(fn(wl), dtype=np.float64)
    fw = band_fwhm(fwhm, wl)
    sig = fw / (2.0 * np.sqrt(2.0 * np.log(2.0)))
    # the same ±5σ support as the calibration's band_average (GAUSS_SUPPORT_SIGMA), in steps
    # of σ/20: a camera's band has no edge at 3σ, and lines beyond it are still seen
    k = GAUSS_SUPPORT_SIGMA
    o = np.linspace(-k, k, int(round(40 * k)) + 1)
    w = np.exp(-0.5 * o * o)
    x = wl[:, None] + sig[:, None] * o[None, :]
    return (np.asarray(fn(x), dtype=np.float64) * w).sum(axis=1) / w.sum()


def relative_band_spd(fn, wl_key: tuple[float, ...], fw_key: tuple[float, ...] | None,
                      what: str) -> np.ndarray:
    """A light's SPD ``fn(λ)`` as the bands see it (:func:`srf_average`), clipped at 0 and scaled
    to a mean of 1 over 400–700 nm; read-only float64 ``(bands,)``. ``what`` names the light
    in the error for one with no power at these wavelengths."""
    wl = np.asarray(wl_key)
    spd = np.clip(srf_average(fn, wl, None if fw_key is None else np.asarray(fw_key)), 0.0, None)
    vis = (wl >= 400) & (wl <= 700)
    norm = spd[vis].mean() if vis.any() else spd.mean()
    if not norm > 0:
        raise InputError(f"{what} has no power at the scene wavelengths")
    out = spd / norm
    out.setflags(write=False)
    return out


def band_fwhm(fwhm, wavelengths: np.ndarray) -> np.ndarray:
    """float64 ``(bands,)`` band widths (nm) from a scalar or one value per band, checked."""
    wl = np.asarray(wavelengths).reshape(-1)
    fw = np.asarray(fwhm, dtype=np.float64)
    if fw.ndim and fw.size != wl.size:
        raise InputError(f"fwhm has {fw.size} values for {wl.size} band centres")
    fw = np.broadcast_to(fw.reshape(-1) if fw.ndim else fw, wl.shape).copy()
    if not np.all(np.isfinite(fw) & (fw >= 0)):
        raise InputError("band fwhm must be finite and >= 0 nm")
    return fw


def check_wavelengths(wavelengths, what: str = "scene") -> np.ndarray:
    """float64 ``(bands,)`` band centres, refused unless finite and in nanometres."""
    wl = np.asarray(wavelengths, dtype=np.float64)
    if wl.ndim != 1 or wl.size == 0 or not np.all(np.isfinite(wl)):
        raise InputError(f"{what} wavelengths must be a non-empty 1-D list of finite values (nm), "
                         f"got shape {wl.shape}")
    # the measured spectra are tabulated in nm: µm (0.4–1.0) or Å would silently give flat spectra
    if wl.min() < 100.0 or wl.max() > 3000.0:
        raise InputError(f"{what} wavelengths must be in nm (100–3000), got "
                         f"{wl.min():g}..{wl.max():g}; convert µm or Å to nm")
    return wl


def _extend(wl_src: np.ndarray, values: np.ndarray, wl: np.ndarray) -> np.ndarray:
    """Linear interpolation inside the table; its first / last value outside."""
    return np.interp(wl, wl_src, values, left=values[0], right=values[-1])


@lru_cache(maxsize=16)
def _illuminant(name: str, wl_key: tuple[float, ...], fw_key: tuple[float, ...] | None = None) -> np.ndarray:
    import colour

    if name not in colour.SDS_ILLUMINANTS:
        raise InputError(f"unknown illuminant {name!r}; use one of colour.SDS_ILLUMINANTS "
                         "(D65, A, HP1, FL2, FL11, LED-B3, …)")
    return relative_band_spd(light_function(name), wl_key, fw_key, f"illuminant {name!r}")


def illuminant_spectrum(name: str, wavelengths: np.ndarray, fwhm: np.ndarray | float | None = None) -> np.ndarray:
    """Relative SPD of a CIE illuminant at ``wavelengths``, mean 1 over 400–700 nm. Shape ``(bands,)``.

    With ``fwhm`` (nm, scalar or per band) each value is the mean over that band's
    Gaussian response (what the camera sees); without, the SPD at the centres.
    """
    wl = np.asarray(wavelengths, dtype=np.float64).reshape(-1)
    fw = None if fwhm is None else tuple(band_fwhm(fwhm, wl).tolist())
    return _illuminant(name, tuple(wl.tolist()), fw)


@lru_cache(maxsize=8)
def _checker(wl_key: tuple[float, ...]) -> np.ndarray:
    import colour

    wl = np.asarray(wl_key)
    sds = colour.SDS_COLOURCHECKERS[_CHECKER]
    out = np.stack([_extend(np.asarray(sd.wavelengths), np.asarray(sd.values, dtype=np.float64), wl)
                    for sd in sds.values()])
    out = np.clip(out, 0.0, 1.0)
    out.setflags(write=False)
    return out


def colorchecker_reflectances(wavelengths: np.ndarray) -> np.ndarray:
    """The 24 ColorChecker reflectances (N. Ohta) at ``wavelengths``; shape ``(24, bands)``, row-major chart order."""
    return _checker(tuple(np.asarray(wavelengths, dtype=np.float64).tolist()))


@dataclass
class Scene:
    """A simulated scene.

    Attributes
    ----------
    name
        Scene kind or a user label.
    radiance
        float32 ``(lines, samples, bands)`` relative spectral radiance of the
        reference exposure (index 0).
    wavelengths, fwhm
        Band centres and widths (nm), ``(bands,)``.
    moving
        Whether a bright patch drifts between exposures.
    white_radiance
        float32 ``(bands,)`` radiance of the diffuse white reference tile
        (reflectance 0.99 under the scene illuminant at full shading).
    motion_step
        Pixels the moving patch drifts per exposure index.
    info
        Free-form description (illuminant, light source, ratio, seed).
    """

    name: str
    radiance: np.ndarray
    wavelengths: np.ndarray
    fwhm: np.ndarray
    moving: bool = False
    white_radiance: np.ndarray | None = None
    motion_step: float = 0.0
    info: dict[str, Any] = field(default_factory=dict)
    _blob_spectrum: np.ndarray | None = None
    _blob_center: tuple[float, float] = (0.0, 0.0)
    _blob_radius: float = 0.0

    @property
    def shape(self) -> tuple[int, int, int]:
        return tuple(self.radiance.shape)  # type: ignore[return-value]

    def _blob(self, exposure_index: float, rows: slice | None = None) -> np.ndarray:
        """float32 ``(lines, samples)`` weight of the moving patch (compact support) at an exposure."""
        lines, samples = self.radiance.shape[:2]
        r = np.arange(lines, dtype=np.float32)[rows if rows is not None else slice(None)]
        cy, cx = self._blob_center
        cx = cx + self.motion_step * float(exposure_index)
        d2 = ((r[:, None] - cy) ** 2 + (np.arange(samples, dtype=np.float32)[None, :] - cx) ** 2)
        rho = np.sqrt(d2) / self._blob_radius
        # A raised-cosine window: smooth, and exactly zero outside the radius.
        return np.where(rho < 1.0, 0.5 * (1.0 + np.cos(np.pi * np.minimum(rho, 1.0))), 0.0).astype(np.float32)

    def radiance_at(self, exposure_index: float = 0, rows: slice | None = None) -> np.ndarray:
        """Radiance seen during exposure ``exposure_index`` (float32 ``(lines, samples, bands)``).

        Without motion this is :attr:`radiance` itself (no copy). With motion a
        bright patch ("cloud") drifts by ``motion_step`` samples per exposure
        index; fractional indices interpolate the drift. ``rows`` selects lines.
        """
        base = self.radiance if rows is None else self.radiance[rows]
        if not self.moving or self._blob_spectrum is None or exposure_index == 0:
            return base
        # The cloud adds light (a glint/cloud in front of a dark background):
        # radiance_k = scene + w_k·cloud, and ``radiance`` already holds w_0·cloud.
        dw = self._blob(exposure_index, rows) - self._blob(0, rows)
        out = base + dw[..., None] * self._blob_spectrum[None, None, :]
        return np.maximum(out, 0.0, out=out).astype(np.float32, copy=False)

    def motion_mask(self, exposure_index: float, *, rtol: float = 1e-3) -> np.ndarray:
        """bool ``(lines, samples)``: pixels whose radiance at ``exposure_index`` differs from exposure 0."""
        return self.moved_between([0, exposure_index], rtol=rtol)

    def moved_mask(self, n_exposures: int = 3) -> np.ndarray:
        """bool ``(lines, samples)``: pixels that change between any of exposures ``0..n_exposures-1``."""
        return self.moved_between(range(n_exposures))

    def moved_between(self, phases, *, rtol: float = 1e-3) -> np.ndarray:
        """bool ``(lines, samples)``: pixels whose radiance at any of ``phases`` (exposure
        indices, e.g. :func:`~mehs.capture.simulate.motion_phase` of each exposure's time)
        differs from that at ``phases[0]`` by more than ``rtol`` of its largest band."""
        lines, samples = self.radiance.shape[:2]
        moved = np.zeros((lines, samples), dtype=bool)
        phases = list(phases)
        if not self.moving or len(phases) < 2:
            return moved
        a = self.radiance_at(phases[0])
        ref = rtol * np.maximum(np.abs(a).max(axis=2), 1e-6)
        for p in phases[1:]:
            moved |= np.abs(self.radiance_at(p) - a).max(axis=2) > ref
        return moved


def _smooth_noise(rng: np.random.Generator, shape: tuple[int, int], scale: float) -> np.ndarray:
    """Low-pass Gaussian noise of unit std (a paper-like texture), float32 ``shape``."""
    from scipy.ndimage import gaussian_filter

    n = rng.standard_normal(shape)
    n = gaussian_filter(n, sigma=scale, mode="wrap")
    s = n.std()
    return (n / s if s > 0 else n).astype(np.float32)


def make_scene(kind: str = "colorchecker", lines: int = 64, samples: int = 64,
               wavelengths: np.ndarray | None = None, illuminant: str | None = None,
               light_source: str | None = None, source_ratio: float = 1000.0,
               motion: bool = False, seed: int = 0, *, fwhm: np.ndarray | None = None,
               shading: float = 0.45, texture: float = 0.03) -> Scene:
    """Build a simulated HDR scene.

    Parameters
    ----------
    kind
        ``"colorchecker"`` — the 24 patches under ``illuminant`` (default D65)
        with a visible lamp of ``light_source`` SPD (default: the illuminant);
        ``"lamp"`` — the chart under a high-pressure sodium lamp (HP1) that is
        itself in view; ``"window"`` — the chart under tungsten light (A) with a
        daylight window (D65) in view; ``"ramp"`` — 8 neutral patches stepping
        down over 4 decades of reflectance from left to right (the chart's
        white spectrum, scaled), handy for response recovery. Its lamp sits on
        the brightest step, so the radiance still falls monotonically, but the
        lamp's glare (2 % of it at the rim, falling as 1/r³) floors the far
        steps at ≈ 0.6 % of the white at ``source_ratio=1000``: 4 decades of
        radiance need ``source_ratio=0`` (the demo's response ladder).
    lines, samples
        Spatial size (the scan direction is ``lines``).
    wavelengths
        Band centres in nm; default :data:`SPECIM_IQ_WAVELENGTHS`.
    illuminant, light_source
        Names in ``colour.SDS_ILLUMINANTS``. ``source_ratio <= 0`` removes the
        visible source.
    source_ratio
        Mean visible radiance of the light source relative to the diffuse white
        (1); the source is surrounded by a glow that falls off as 1/r³.
    motion
        Add a bright patch that drifts between exposures (ghost tests).
    seed
        Seeds the texture (the scene is deterministic given its arguments).
    shading
        Relative illumination fall-off across the frame (0 = uniform).
    texture
        Std of the multiplicative paper texture.

    Returns
    -------
    Scene
        With float32 radiance ``(lines, samples, bands)``.
    """
    from mehs.calibration.targets import TARGET_KINDS, make_target_scene

    if kind in TARGET_KINDS:   # uniform calibration targets (sphere, panel)
        return make_target_scene(kind, lines, samples, wavelengths, illuminant=illuminant,
                                 fwhm=fwhm, seed=seed)
    if kind not in SCENE_KINDS:
        raise InputError(f"unknown scene kind {kind!r}; use one of "
                         f"{', '.join(SCENE_KINDS + TARGET_KINDS)}")
    if lines < 4 or samples < 4:
        raise InputError(f"scene size must be at least 4×4, got {lines}×{samples}")
    if not np.isfinite(source_ratio):
        raise InputError(f"source_ratio must be finite, got {source_ratio}")
    wl = SPECIM_IQ_WAVELENGTHS.copy() if wavelengths is None else check_wavelengths(wavelengths)
    if fwhm is None:
        fwhm = SPECIM_IQ_FWHM.copy() if wavelengths is None else np.full(wl.size, 7.0)
    fwhm = band_fwhm(fwhm, wl)
    defaults = {"colorchecker": ("D65", None), "lamp": ("HP1", "HP1"),
                "window": ("A", "D65"), "ramp": ("D65", None)}
    ill_name = illuminant or defaults[kind][0]
    src_name = light_source or defaults[kind][1] or ill_name
    ill = illuminant_spectrum(ill_name, wl, fwhm)
    src = illuminant_spectrum(src_name, wl, fwhm)
    rng = np.random.default_rng(seed)

    yy, xx = np.mgrid[0:lines, 0:samples].astype(np.float32)
    v, u = yy / max(lines - 1, 1), xx / max(samples - 1, 1)

    refl = colorchecker_reflectances(wl)
    # Background: a matte dark-grey board (the chart's frame).
    table = np.vstack([refl, np.full((1, wl.size), 0.04)])
    bg = table.shape[0] - 1
    labels = np.full((lines, samples), bg, dtype=np.int32)
    if kind == "ramp":
        # 8 neutral steps, each a factor of ~3.7 (4 decades overall).
        steps = 8
        grey = refl[18]  # the chart's white patch spectrum, scaled
        factors = np.logspace(0, -4, steps)
        # scaled by its peak, not its mean: by the mean the top step reflected 102 % of the
        # light in the red, more than a non-fluorescent surface can
        table = np.vstack([grey[None, :] * factors[:, None] / grey.max(), np.full((1, wl.size), 0.04)])
        bg = steps
        labels[:] = np.clip((u * steps).astype(np.int32), 0, steps - 1)
        labels[(v < 0.06) | (v > 0.94)] = bg
    else:
        # The chart occupies the left ~75 % of the frame; 4 rows × 6 columns with black gaps.
        x0, x1, y0, y1 = 0.04, 0.74, 0.10, 0.90
        cu = (u - x0) / (x1 - x0) * 6
        cv = (v - y0) / (y1 - y0) * 4
        inside = (cu >= 0) & (cu < 6) & (cv >= 0) & (cv < 4)
        fu, fv = cu - np.floor(cu), cv - np.floor(cv)
        on_patch = inside & (fu > 0.1) & (fu < 0.9) & (fv > 0.1) & (fv < 0.9)
        labels[on_patch] = (np.floor(cv) * 6 + np.floor(cu)).astype(np.int32)[on_patch]

    # Smooth shading (a light from the upper left) and a multiplicative texture.
    shade = (1.0 - shading * (0.6 * u + 0.4 * v)).astype(np.float32)
    tex = (1.0 + texture * _smooth_noise(rng, (lines, samples), max(1.0, min(lines, samples) / 48))
           ).astype(np.float32)
    gain = shade * np.clip(tex, 0.5, 1.5)
    spectra = (table * ill[None, :]).astype(np.float32)
    radiance = spectra[labels]
    radiance *= gain[..., None]

    info = {"kind": kind, "illuminant": ill_name, "light_source": src_name if source_ratio > 0 else None,
            "source_ratio": float(source_ratio), "seed": int(seed), "shading": shading, "texture": texture}
    if source_ratio > 0:
        if kind == "window":
            # A rectangular daylight window (uniform, very bright) at the right.
            win = (u > 0.80) & (u < 0.96) & (v > 0.12) & (v < 0.48)
            radiance[win] = (src * source_ratio).astype(np.float32)
            info["source_pixels"] = int(win.sum())
        else:
            # A round lamp with a 1/r³ glow around it, on the right of the frame; on a ramp,
            # on its brightest step: over the darkest ones it hid them, and its glare turned
            # the ramp round (steps 4–8 brightened towards the lamp, as bright as the chart's)
            cy, cx = 0.30 * (lines - 1), (0.5 / 8 if kind == "ramp" else 0.86) * (samples - 1)
            rad = max(1.5, 0.06 * min(lines, samples))
            r = np.sqrt((yy - cy) ** 2 + (xx - cx) ** 2)
            core = r <= rad
            # Scattered light: 2 % of the lamp at its rim, falling as 1/r³.
            glow = np.where(core, 0.0, 0.02 * source_ratio * (rad / np.maximum(r, rad)) ** 3)
            radiance += glow[..., None].astype(np.float32) * src[None, None, :].astype(np.float32)
            radiance[core] = (src * source_ratio).astype(np.float32)
            info["source_pixels"] = int(core.sum())

    scene = Scene(name=kind, radiance=np.ascontiguousarray(radiance, dtype=np.float32),
                  wavelengths=wl, fwhm=np.asarray(fwhm, dtype=np.float64), moving=bool(motion),
                  white_radiance=(0.99 * ill).astype(np.float32), info=info)
    if motion:
        # A bright "cloud" (up to 3× the diffuse white, daylight SPD) drifting right.
        scene._blob_spectrum = (3.0 * illuminant_spectrum("D65", wl, fwhm)).astype(np.float32)
        scene._blob_center = (0.72 * (lines - 1), 0.25 * (samples - 1))
        scene._blob_radius = max(2.0, 0.12 * min(lines, samples))
        scene.motion_step = max(1.0, 0.06 * samples)
        scene.radiance += scene._blob(0)[..., None] * scene._blob_spectrum[None, None, :]
        info["motion_step"] = scene.motion_step
    return scene
