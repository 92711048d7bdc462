"""Thin-film / multilayer reflectance: optical constants and the transfer-matrix method.

Optical constants (complex index ``N = n + i k``, the ``e^{-iωt}`` convention, so an
absorbing medium has ``k > 0``):

========  =========================================================  ================
name      source                                                     range
========  =========================================================  ================
``SiO2``  Malitson 1965 Sellmeier (fused silica, 20 °C), k = 0        210–3710 nm
``Si``    Green 2008, crystalline Si at 300 K (``data/Si_Green2008``)  350–800 nm
``Al``    McPeak et al. 2015, evaporated Al (``data/Al_McPeak2015``)   350–800 nm
``air``   1                                                          any
========  =========================================================  ================

Tables are interpolated linearly in n and k; a wavelength outside a table is an error.

Reflectance of a stack ``ambient | layer_1 … layer_L | substrate`` at incidence angle
θ₀ (:func:`reflectance_TMM`): the 2×2 transfer-matrix method for s and p polarisation
(Byrnes' formulation), unpolarised ``R = (R_s + R_p) / 2``. For one film the result is
Airy's closed form ``r = (r₀₁ + r₁₂ e^{2iδ}) / (1 + r₀₁ r₁₂ e^{2iδ})``,
``δ = 2π N₁ d cos θ₁ / λ`` (:func:`reflectance_Airy`).

References
----------
- Malitson, I. H. (1965). Interspecimen comparison of the refractive index of fused
  silica. JOSA 55(10), 1205–1209.
- Green, M. A. (2008). Self-consistent optical parameters of intrinsic silicon at 300 K
  including temperature coefficients. Sol. Energ. Mat. Sol. Cells 92, 1305–1310.
- McPeak, K. M. et al. (2015). Plasmonic films can easily be better: rules and recipes.
  ACS Photonics 2, 326–333.
- Born, M. & Wolf, E. Principles of Optics, §1.6 (stratified media, Airy formulae).
- Byrnes, S. J. (2016). Multilayer optical calculations. arXiv:1603.02720.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path

import numpy as np

from mehs.errors import InputError

DATA_DIR = Path(__file__).with_name("data")

# Malitson 1965: n² − 1 = Σ B_i λ² / (λ² − C_i²), λ in µm
_MALITSON_B = np.array([0.6961663, 0.4079426, 0.8974794])
_MALITSON_C = np.array([0.0684043, 0.1162414, 9.896161])


def index_SiO2_Malitson1965(wavelengths_nm: np.ndarray) -> np.ndarray:
    """Refractive index of fused silica ``(L,)`` complex (k = 0) at ``wavelengths_nm`` (L,)."""
    lam = np.asarray(wavelengths_nm, dtype=np.float64) / 1000.0
    if np.any((lam < 0.21) | (lam > 3.71)):
        raise InputError("Malitson's SiO2 Sellmeier is valid for 210–3710 nm")
    l2 = lam[..., None] ** 2
    n2 = 1.0 + np.sum(_MALITSON_B * l2 / (l2 - _MALITSON_C ** 2), axis=-1)
    return np.sqrt(n2).astype(np.complex128)


@lru_cache(maxsize=None)
def _nk_table(name: str) -> np.ndarray:
    rows = [ln for ln in (DATA_DIR / name).read_text(encoding="utf-8").splitlines()
            if ln.strip() and not ln.startswith("#") and not ln.startswith("wavelength")]
    return np.array([[float(x) for x in ln.split(",")] for ln in rows], dtype=np.float64)


def _tabulated(name: str, label: str):
    def index(wavelengths_nm: np.ndarray) -> np.ndarray:
        t = _nk_table(name)
        lam = np.asarray(wavelengths_nm, dtype=np.float64)
        if np.any((lam < t[0, 0]) | (lam > t[-1, 0])):
            raise InputError(f"{label} optical constants cover {t[0, 0]:g}–{t[-1, 0]:g} nm; "
                             f"asked for {lam.min():g}–{lam.max():g} nm")
        return np.interp(lam, t[:, 0], t[:, 1]) + 1j * np.interp(lam, t[:, 0], t[:, 2])
    index.__doc__ = f"Complex index of {label} ``(L,)`` at ``wavelengths_nm`` (table {name})."
    return index


def _air(wavelengths_nm: np.ndarray) -> np.ndarray:
    return np.ones(np.shape(wavelengths_nm), dtype=np.complex128)


#: name → function ``wavelengths_nm (L,) → complex index (L,)``
MATERIALS = {
    "SiO2": index_SiO2_Malitson1965,
    "Si": _tabulated("Si_Green2008.csv", "silicon (Green 2008)"),
    "Al": _tabulated("Al_McPeak2015.csv", "aluminium (McPeak 2015)"),
    "air": _air,
}


def refractive_index(name: str, wavelengths_nm: np.ndarray) -> np.ndarray:
    """Complex index ``(L,)`` of a named material (see :data:`MATERIALS`)."""
    try:
        fn = MATERIALS[name]
    except KeyError:
        raise InputError(f"unknown material {name!r}; known: {', '.join(MATERIALS)}") from None
    return fn(wavelengths_nm)


def _cos_in_layer(n_j: np.ndarray, n0_sin0: np.ndarray) -> np.ndarray:
    """cos θ_j (complex) with the forward-propagating branch (Im(N cos θ) ≥ 0)."""
    cos = np.sqrt(1.0 - (n0_sin0 / n_j) ** 2 + 0j)
    kz = n_j * cos
    flip = (kz.imag < 0) | ((np.abs(kz.imag) < 1e-14) & (kz.real < 0))
    return np.where(flip, -cos, cos)


def _fresnel(n_i, cos_i, n_j, cos_j, pol: str):
    if pol == "s":
        den = n_i * cos_i + n_j * cos_j
        return (n_i * cos_i - n_j * cos_j) / den, 2 * n_i * cos_i / den
    den = n_j * cos_i + n_i * cos_j
    return (n_j * cos_i - n_i * cos_j) / den, 2 * n_i * cos_i / den


def amplitude_TMM(indices: list[np.ndarray], thicknesses_nm: list[float],
                  wavelengths_nm: np.ndarray, cos_theta0: np.ndarray, pol: str) -> np.ndarray:
    """Complex reflection amplitude of a layer stack, broadcast over λ and angle.

    Parameters
    ----------
    indices
        Complex indices, each broadcastable to the output: ambient, layers…, substrate.
    thicknesses_nm
        One per inner layer (``len(indices) - 2``).
    wavelengths_nm, cos_theta0
        Broadcastable arrays (e.g. ``(L, 1)`` and ``(1, C)``); θ₀ in the ambient.
    pol
        ``"s"`` or ``"p"``.
    """
    if len(thicknesses_nm) != len(indices) - 2:
        raise ValueError("one thickness per inner layer")
    lam = np.asarray(wavelengths_nm, dtype=np.float64)
    c0 = np.asarray(cos_theta0, dtype=np.float64)
    n0 = indices[0]
    n0_sin0 = n0 * np.sqrt(np.clip(1.0 - c0 ** 2, 0.0, None))
    cos = [_cos_in_layer(n, n0_sin0) for n in indices]
    # M = (1/t01)[[1, r01],[r01, 1]] · Π_j P_j · (1/t_j,j+1)[[1, r],[r, 1]]; the 1/t
    # factors are common to M00 and M10 and cancel in r = M10/M00, so they are left
    # out: that keeps grazing incidence (t01 = 0, r = -1) finite.
    r, _ = _fresnel(indices[0], cos[0], indices[1], cos[1], pol)
    m00, m01, m10, m11 = np.ones_like(r), r, r, np.ones_like(r)
    for j, d in enumerate(thicknesses_nm, start=1):
        delta = 2 * np.pi * indices[j] * cos[j] * float(d) / lam
        e_m, e_p = np.exp(-1j * delta), np.exp(1j * delta)
        r, _ = _fresnel(indices[j], cos[j], indices[j + 1], cos[j + 1], pol)
        # P = diag(e^{-iδ}, e^{iδ}); L = [[1, r], [r, 1]] (1/t dropped); M ← M · P · L
        a00, a01, a10, a11 = e_m, e_m * r, e_p * r, e_p
        m00, m01, m10, m11 = (m00 * a00 + m01 * a10, m00 * a01 + m01 * a11,
                              m10 * a00 + m11 * a10, m10 * a01 + m11 * a11)
    return m10 / m00


def reflectance_TMM(indices: list[np.ndarray], thicknesses_nm: list[float],
                    wavelengths_nm: np.ndarray, cos_theta0: np.ndarray) -> np.ndarray:
    """Unpolarised reflectance ``(|r_s|² + |r_p|²) / 2`` of a stack (see :func:`amplitude_TMM`)."""
    rs = amplitude_TMM(indices, thicknesses_nm, wavelengths_nm, cos_theta0, "s")
    rp = amplitude_TMM(indices, thicknesses_nm, wavelengths_nm, cos_theta0, "p")
    return 0.5 * (np.abs(rs) ** 2 + np.abs(rp) ** 2)


def reflectance_Airy(n0, n1, n2, d_nm: float, wavelengths_nm: np.ndarray) -> np.ndarray:
    """Normal-incidence reflectance of one film ``n1`` (thickness ``d_nm``) on ``n2``."""
    lam = np.asarray(wavelengths_nm, dtype=np.float64)
    r01 = (n0 - n1) / (n0 + n1)
    r12 = (n1 - n2) / (n1 + n2)
    e = np.exp(2j * (2 * np.pi * n1 * d_nm / lam))
    return np.abs((r01 + r12 * e) / (1 + r01 * r12 * e)) ** 2


@dataclass(frozen=True)
class FilmStack:
    """Films (top first) on a substrate, in air.

    ``layers``: ``((material, thickness_nm), …)``; ``substrate``: a material name.
    """

    layers: tuple[tuple[str, float], ...]
    substrate: str = "Si"

    def reflectance(self, wavelengths_nm: np.ndarray, cos_theta: np.ndarray) -> np.ndarray:
        """Unpolarised reflectance ``(L, C)`` at ``wavelengths_nm`` (L,) × ``cos_theta`` (C,)."""
        lam = np.asarray(wavelengths_nm, dtype=np.float64)
        idx = [refractive_index("air", lam)] + [refractive_index(m, lam) for m, _ in self.layers]
        idx.append(refractive_index(self.substrate, lam))
        idx = [n[:, None] for n in idx]
        c = np.clip(np.asarray(cos_theta, dtype=np.float64), 0.0, 1.0)[None, :]
        return reflectance_TMM(idx, [d for _, d in self.layers], lam[:, None], c)

    def label(self) -> str:
        films = " + ".join(f"{d:g} nm {m}" for m, d in self.layers)
        return f"{films} on {self.substrate}" if films else f"bare {self.substrate}"


_LAYER_RE = re.compile(r"^\s*([A-Za-z][A-Za-z0-9]*)\s*:\s*([0-9]*\.?[0-9]+)\s*nm\s*$")


def parse_material(spec: str):
    """Parse ``--material``: ``diffuse[:ρ]`` or ``thin-film:M:Dnm[,M:Dnm…][@SUBSTRATE]``.

    Returns ``("diffuse", ρ)`` or ``("thin-film", FilmStack)``. Films are listed top
    first; the substrate defaults to Si (the paper's 400 nm SiO₂ + 5 nm Al stack is
    ``thin-film:Al:5nm,SiO2:400nm``).
    """
    s = spec.strip()
    if s == "diffuse" or s.startswith("diffuse:"):
        try:
            rho = float(s.split(":", 1)[1]) if ":" in s else 1.0
        except ValueError:
            raise InputError(f"--material {spec!r}: diffuse takes a reflectance, e.g. diffuse:0.8") from None
        if not 0.0 <= rho <= 1.0:
            raise InputError(f"--material {spec!r}: reflectance must be in [0, 1]")
        return "diffuse", rho
    if not s.startswith("thin-film:"):
        raise InputError(f"--material {spec!r}: use diffuse[:ρ] or thin-film:SiO2:300nm "
                         "(films top first, comma-separated; '@Al' to change the Si substrate)")
    body = s[len("thin-film:"):]
    substrate = "Si"
    if "@" in body:
        body, substrate = body.rsplit("@", 1)
        substrate = substrate.strip()
    layers = []
    for part in filter(None, body.split(",")):
        m = _LAYER_RE.match(part)
        if not m:
            raise InputError(f"--material {spec!r}: layer {part!r} is not MATERIAL:THICKNESSnm")
        layers.append((m.group(1), float(m.group(2))))
    for name in [m for m, _ in layers] + [substrate]:
        if name not in MATERIALS:
            raise InputError(f"--material {spec!r}: unknown material {name!r}; known: "
                             f"{', '.join(MATERIALS)}")
    return "thin-film", FilmStack(tuple(layers), substrate)


#: wavelength grid of the spectral reflectance tables the BSDF interpolates (nm)
TABLE_WAVELENGTHS = np.arange(360.0, 801.0, 2.0)
TABLE_COS = np.linspace(0.0, 1.0, 129)


def spectral_table(stack: FilmStack) -> np.ndarray:
    """Reflectance ``(len(TABLE_WAVELENGTHS), len(TABLE_COS))`` for the spectral BSDF."""
    return stack.reflectance(TABLE_WAVELENGTHS, TABLE_COS)


def rgb_table(stack: FilmStack, wavelengths_nm: np.ndarray = np.arange(400.0, 701.0, 10.0)
              ) -> np.ndarray:
    """Linear-sRGB reflectance ``(3, len(TABLE_COS))`` for an RGB renderer.

    The spectral reflectance is integrated against D65 (the sRGB white) and the CIE 1931
    observer and expressed in sRGB, so a perfect white reflector gives (1, 1, 1) — what an
    RGB renderer stores as the material's colour.
    """
    from mehs.rgb import XYZ_to_linear_sRGB, spectra_to_XYZ
    from mehs.capture.scene import illuminant_spectrum

    lam = np.asarray(wavelengths_nm, dtype=np.float64)
    d65 = illuminant_spectrum("D65", lam)
    refl = stack.reflectance(lam, TABLE_COS).T                      # (C, L)
    xyz = spectra_to_XYZ(refl * d65, lam)                             # (C, 3)
    white = spectra_to_XYZ(d65[None, :], lam)[0]
    rgb = XYZ_to_linear_sRGB(xyz / white[1], clip_negative=True)
    rgb_white = XYZ_to_linear_sRGB(white[None, :] / white[1], clip_negative=False)[0]
    return np.clip(rgb / rgb_white, 0.0, None).T
