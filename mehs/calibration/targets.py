"""Calibration targets for the simulated camera: an integrating sphere and a diffuse panel.

The simulator's radiance unit is W·sr⁻¹·m⁻²·nm⁻¹ (a diffuse white under its
normalised illuminants has about 1/π·π ≈ 1: full daylight on paper is of that
order), so a simulated calibrated source is *absolute* in the same unit as the
scenes' ground truth — which is what lets a test hold calibrated cubes against
the truth.

- ``"sphere"``: an integrating sphere filling the view, a quartz-tungsten-halogen
  lamp modelled as Planck's law at :data:`SPHERE_CCT` K, mean radiance
  :data:`SPHERE_LEVEL` over 400–700 nm; :func:`sphere_certificate` writes its
  calibration certificate (5 nm steps, 350–1100 nm, with a relative
  uncertainty column) as a lab receives it;
- ``"panel"``: a 99 % diffuse panel (flat reflectance) under a CIE illuminant
  filling the view (relative calibration, ``mehs calibrate --panel``).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

#: kinds served by :func:`make_target_scene` (``mehs capture --simulate --scene sphere``)
TARGET_KINDS = ("sphere", "panel")
SPHERE_CCT = 3000.0
SPHERE_LEVEL = 0.5
#: relative standard uncertainty written on the simulated certificate
SPHERE_CERT_UNCERTAINTY = 0.01


def planck_relative(wavelengths_nm: np.ndarray, cct: float = SPHERE_CCT) -> np.ndarray:
    """Planck's law at ``cct`` K, scaled to a mean of 1 over 400–700 nm. Shape of the input."""
    from mehs.capture.scene import planck

    return planck(wavelengths_nm, cct) / np.mean(planck(np.arange(400.0, 701.0, 1.0), cct))


def sphere_radiance(wavelengths_nm: np.ndarray, level: float = SPHERE_LEVEL) -> np.ndarray:
    """The simulated sphere's spectral radiance (W·sr⁻¹·m⁻²·nm⁻¹) at ``wavelengths_nm``."""
    return level * planck_relative(wavelengths_nm)


def make_target_scene(kind: str, lines: int, samples: int, wavelengths=None, *,
                      illuminant: str | None = None, fwhm=None, seed: int = 0,
                      level: float = SPHERE_LEVEL):
    """A uniform calibration target as a :class:`~mehs.capture.scene.Scene`."""
    from mehs.capture.scene import SPECIM_IQ_FWHM, SPECIM_IQ_WAVELENGTHS, Scene, illuminant_spectrum
    from mehs.errors import InputError

    wl = SPECIM_IQ_WAVELENGTHS if wavelengths is None else np.asarray(wavelengths, dtype=np.float64)
    fw = (SPECIM_IQ_FWHM if wavelengths is None else np.full(wl.size, 7.0)) if fwhm is None else fwhm
    if kind == "sphere":
        spec = sphere_radiance(wl, level)
        info = {"kind": "sphere", "source": f"Planck {SPHERE_CCT:g} K", "level": level,
                "unit": "W sr-1 m-2 nm-1", "certificate": "truth/source_radiance.csv"}
    elif kind == "panel":
        name = illuminant or "D65"
        # ρ·E/π, the simulator's illuminants being normalised so that E/π = S; averaged
        # over each band's response as the scenes' lights are (a lamp's lines!)
        spec = 0.99 * illuminant_spectrum(name, wl, fw)
        info = {"kind": "panel", "illuminant": name, "reflectance": 0.99,
                "unit": "W sr-1 m-2 nm-1"}
    else:
        raise InputError(f"unknown calibration target {kind!r}; use one of {TARGET_KINDS}")
    cube = np.broadcast_to(spec.astype(np.float32), (int(lines), int(samples), wl.size)).copy()
    return Scene(kind, cube, wl, np.asarray(fw, dtype=np.float64), white_radiance=spec.astype(np.float32),
                 info=info)


def sphere_certificate(path: str | Path, level: float = SPHERE_LEVEL) -> Path:
    """Write the simulated sphere's certificate: ``wavelength_nm,radiance,rel_uncertainty``."""
    from mehs.io.atomic import atomic_path

    wl = np.arange(350.0, 1100.0 + 1e-9, 5.0)
    L = sphere_radiance(wl, level)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    lines = ["# simulated integrating sphere (mehs), QTH lamp as Planck %g K" % SPHERE_CCT,
             "# spectral radiance in W sr-1 m-2 nm-1; third column: relative standard uncertainty",
             "wavelength_nm,radiance,rel_uncertainty"]
    lines += [f"{w:.1f},{v:.8e},{SPHERE_CERT_UNCERTAINTY}" for w, v in zip(wl, L)]
    with atomic_path(path) as tmp:
        Path(tmp).write_text("\n".join(lines) + "\n", encoding="utf-8")
    return path
