"""Measured spectra for natural scenes: reflectances and lights, split into disjoint pools.

Materials are every measured reflectance colour-science ships (deduplicated):

- the 99 CIE 2017 colour-fidelity test samples (``load_TCS_CIE2017``; CIE 224:2017),
- the 190 rawtoaces camera-characterisation training patches
  (``read_training_data_rawtoaces_v1``; AMPAS rawtoaces),
- the ColorChecker sets (N. Ohta, BabelColor average, ISO 17321-1) and the PMC skin set,
- the CIE 13.3 test-colour samples (``SDS_TCS``) and the NIST CQS samples (``SDS_VS``).

Lights come in families; the daylight and tungsten families are continuous (CIE D series at a
correlated colour temperature, Planck at a temperature), the others are the measured SPDs of
``colour.SDS_ILLUMINANTS`` and ``colour.SDS_LIGHT_SOURCES``.

Pools
-----
Each material and each light (for continuous families: each CCT bin) is ranked within its
family by ``sha256(key)``; rank mod 5 gives the pool: 0–2 train, 3 val, 4 test. The pools are
disjoint, fixed (independent of any seed and of the scene size) and every family with at least
5 members has a member in every pool, so a test scene's materials and lights are never seen in
training.

Spectra outside the tables
--------------------------
As :mod:`mehs.capture.scene`: reflectances hold their last tabulated value beyond the table;
measured lights continue as :mod:`mehs.scenes.lights` says (illuminant A by its formula,
tungsten lamps by Planck's law, the others with the mean of their last 20 nm); D series and
Planck are evaluated (D series beyond 830 nm: the tail mean). Everything is clipped at 0 (reflectance also at 1). Lights are
averaged over each band's Gaussian response when a ``fwhm`` is given (see
:mod:`mehs.capture.scene`, "Band values").

References
----------
- CIE 224:2017 Colour fidelity index for accurate scientific use (99 test samples).
- Academy of Motion Picture Arts and Sciences, rawtoaces training spectra (190 patches).
- CIE 13.3-1995 Method of measuring and specifying colour rendering properties of light sources.
- Davis & Ohno (2010), "Color quality scale", Opt. Eng. 49(3) 033602 (NIST CQS samples).
- CIE 015:2018 Colorimetry (D series, illuminants A, F, HP, LED).
- Judd, MacAdam & Wyszecki (1964), "Spectral distribution of typical daylight as a function
  of correlated color temperature", JOSA 54(8).
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass
from functools import lru_cache

import numpy as np

from mehs.errors import InputError

#: Pool names, and ``"all"`` (every pool together: for captures that are not split).
POOLS = ("train", "val", "test")
POOL_CHOICES = POOLS + ("all",)

#: Light families and the kind of lighting each one serves.
LIGHT_FAMILIES = ("sun", "sky", "tungsten", "fluorescent", "led", "sodium", "discharge")

# Continuous families: (low, high, bin width) of the CCT / temperature in kelvin.
# The sun is the direct beam (yellower), the sky the diffuse light that fills shadows (bluer).
_CONTINUOUS = {"sun": (4000.0, 7000.0, 100.0), "sky": (7500.0, 20000.0, 500.0),
               "tungsten": (2200.0, 3400.0, 50.0)}

_NAMED_LIGHTS = {
    "tungsten": ("A", "Incandescent", "60 A/W (Soft White)", "Neodimium Incandescent",
                 "ISO 7589 Studio Tungsten", "ISO 7589 Photoflood"),
    "fluorescent": ("FL1", "FL2", "FL3", "FL4", "FL5", "FL6", "FL7", "FL8", "FL9", "FL10",
                    "FL11", "FL12", "FL3.1", "FL3.2", "FL3.3", "FL3.4", "FL3.5", "FL3.6",
                    "FL3.7", "FL3.8", "FL3.9", "FL3.10", "FL3.11", "FL3.12", "FL3.13",
                    "FL3.14", "FL3.15", "Philips TL-84", "T8 Luxline Plus White",
                    "T8 Polylux 3000", "T8 Polylux 4000", "Cool White FL", "Daylight FL",
                    "Triphosphor FL", "F32T8/TL830 (Triphosphor)", "F32T8/TL841 (Triphosphor)",
                    "F32T8/TL850 (Triphosphor)", "F34T12WW/RS/EW (Warm White FL)",
                    "F40/C50 (Broadband FL)", "F40/DX (Broadband FL)", "F40/N (Natural FL)"),
    "led": ("LED-B1", "LED-B2", "LED-B3", "LED-B4", "LED-B5", "LED-BH1", "LED-RGB1", "LED-V1",
            "LED-V2", "3-LED-1 (457/540/605)", "3-LED-2 (473/545/616)", "4-LED Yellow",
            "4-LED-1 (461/526/576/624)", "PHOS-1", "PHOS-2", "PHOS-3", "Phosphor LED YAG"),
    # high-pressure sodium only: low-pressure sodium puts all its power in the 589 nm doublet,
    # which no 12-bit exposure of a lamp in view can hold (it is a discharge lamp below)
    "sodium": ("HP1", "HP2", "HPS", "Super HPS", "C100S54 (HPS)", "C100S54C (HPS)",
               "SDW-T 100W/LV (Super HPS)"),
    "discharge": ("HP3", "HP4", "HP5", "Mercury", "Metal Halide", "MHC100/U/MP/3K",
                  "MHC100/U/MP/4K", "H38HT-100 (Mercury)", "LPS"),
}


@dataclass(frozen=True)
class Light:
    """One light: a measured SPD (``name``) or a continuous family at ``kelvin``."""

    family: str
    name: str
    kelvin: float | None = None

    @property
    def label(self) -> str:
        return f"{self.name} {self.kelvin:.0f} K" if self.kelvin is not None else self.name


def _rank_pool(keys: list[str]) -> dict[str, str]:
    ranked = sorted(keys, key=lambda k: hashlib.sha256(k.encode()).hexdigest())
    return {k: ("train", "train", "train", "val", "test")[i % 5] for i, k in enumerate(ranked)}


def check_pool(pool: str) -> str:
    if pool not in POOL_CHOICES:
        raise InputError(f"unknown pool {pool!r}; use one of {', '.join(POOL_CHOICES)}")
    return pool


def _table(wl_src: np.ndarray, values: np.ndarray, wl: np.ndarray, tail_nm: float) -> np.ndarray:
    hi = float(values[wl_src >= wl_src[-1] - tail_nm].mean()) if tail_nm > 0 else values[-1]
    return np.interp(wl, wl_src, values, left=values[0], right=hi)


# --------------------------------------------------------------------------- materials
def _material_sources():
    """``[(set name, sample name, colour SpectralDistribution)]`` of every shipped reflectance."""
    import colour
    from colour.characterisation.aces_it import read_training_data_rawtoaces_v1
    from colour.quality import SDS_TCS, SDS_VS
    from colour.quality.cfi2017 import load_TCS_CIE2017

    out = []
    tcs17 = load_TCS_CIE2017(colour.SpectralShape(380, 780, 5))
    for name, sd in zip(tcs17.labels, tcs17.to_sds()):
        out.append(("CIE 2017 TCS", str(name), sd))
    raw = read_training_data_rawtoaces_v1()
    for name, sd in zip(raw.labels, raw.to_sds()):
        out.append(("rawtoaces training", str(name), sd))
    for set_name in ("ColorChecker N Ohta", "BabelColor Average", "ISO 17321-1", "PMC"):
        for name, sd in colour.SDS_COLOURCHECKERS[set_name].items():
            out.append((set_name, str(name), sd))
    for set_name, sds in list(SDS_TCS.items()) + list(SDS_VS.items()):
        for name, sd in sds.items():
            out.append((str(set_name), str(name), sd))
    return out


@lru_cache(maxsize=8)
def _materials(wl_key: tuple[float, ...]) -> tuple[tuple[tuple[str, str], ...], np.ndarray]:
    wl = np.asarray(wl_key)
    vis = np.arange(400.0, 701.0, 10.0)
    names, rows, vis_rows = [], [], []
    for set_name, name, sd in _material_sources():
        w, v = np.asarray(sd.wavelengths, np.float64), np.asarray(sd.values, np.float64)
        r_vis = np.clip(_table(w, v, vis, 0.0), 0.0, 1.0)
        # repeated samples across sets (TCS 1995 ⊂ 2024, CQS 7.4 ≈ 9.0) would inflate the
        # count of distinct materials and leak between pools
        if vis_rows and np.min(np.abs(np.asarray(vis_rows) - r_vis).max(axis=1)) < 0.005:
            continue
        names.append((set_name, name))
        rows.append(np.clip(_table(w, v, wl, 0.0), 0.0, 1.0))
        vis_rows.append(r_vis)
    table = np.stack(rows)
    table.setflags(write=False)
    return tuple(names), table


def material_library(wavelengths: np.ndarray) -> tuple[list[tuple[str, str]], np.ndarray]:
    """Every distinct measured reflectance at ``wavelengths``.

    Returns
    -------
    names
        ``[(set, sample name)]``, one per row.
    reflectance
        float64 ``(n_materials, bands)`` in [0, 1] (read-only).
    """
    names, table = _materials(tuple(np.asarray(wavelengths, np.float64).tolist()))
    return list(names), table


def material_pools(wavelengths: np.ndarray | None = None) -> dict[str, np.ndarray]:
    """Row indices of :func:`material_library` per pool (disjoint; ``"all"`` = every row)."""
    wl = np.arange(400.0, 701.0, 10.0) if wavelengths is None else wavelengths
    names, _ = material_library(wl)
    keys = [f"{s}/{n}" for s, n in names]
    pool_of = _rank_pool(keys)
    out = {p: np.array([i for i, k in enumerate(keys) if pool_of[k] == p], dtype=np.int64)
           for p in POOLS}
    out["all"] = np.arange(len(keys), dtype=np.int64)
    return out


# --------------------------------------------------------------------------- lights
@lru_cache(maxsize=1)
def _light_pool_table() -> dict[str, dict[str, list]]:
    """``{family: {pool: [Light or (lo, hi) kelvin bin]}}``."""
    out: dict[str, dict[str, list]] = {}
    for fam in LIGHT_FAMILIES:
        items: list = []
        if fam in _CONTINUOUS:
            lo, hi, step = _CONTINUOUS[fam]
            edges = np.arange(lo, hi + 0.5 * step, step)
            items += [(float(a), float(b)) for a, b in zip(edges[:-1], edges[1:])]
        items += [Light(fam, n) for n in _NAMED_LIGHTS.get(fam, ())]
        keys = {(f"{fam}/{it[0]:.0f}-{it[1]:.0f}K" if isinstance(it, tuple) else f"{fam}/{it.name}"): it
                for it in items}
        pool_of = _rank_pool(list(keys))
        out[fam] = {p: [it for k, it in keys.items() if pool_of[k] == p] for p in POOLS}
    return out


def light_pool(family: str, pool: str) -> list:
    """Members of a light ``family`` in ``pool``: :class:`Light` objects and ``(lo, hi)`` K bins."""
    if family not in LIGHT_FAMILIES:
        raise InputError(f"unknown light family {family!r}; use one of {', '.join(LIGHT_FAMILIES)}")
    table = _light_pool_table()[family]
    if check_pool(pool) == "all":
        return [it for p in POOLS for it in table[p]]
    return list(table[pool])


def draw_light(family: str, pool: str, rng: np.random.Generator) -> Light:
    """One light of ``family`` from ``pool`` (a continuous bin gets a uniform kelvin inside it)."""
    members = light_pool(family, pool)
    it = members[int(rng.integers(len(members)))]
    if isinstance(it, tuple):
        name = {"sun": "CIE D (sun)", "sky": "CIE D (sky)", "tungsten": "Planck"}[family]
        return Light(family, name, float(np.round(rng.uniform(*it), 0)))
    return it


@lru_cache(maxsize=64)
def _light_spd(light: Light, wl_key: tuple[float, ...], fw_key: tuple[float, ...] | None = None) -> np.ndarray:
    import colour

    from mehs.capture.scene import relative_band_spd
    from mehs.scenes.lights import light_function, planck

    if light.kelvin is not None and light.family == "tungsten":
        def fn(x):
            return planck(x, light.kelvin)
    elif light.kelvin is not None:
        xy = colour.temperature.CCT_to_xy_CIE_D(light.kelvin * 1.4388 / 1.4380)
        sd = colour.sd_CIE_illuminant_D_series(xy)
        w_src, v_src = np.asarray(sd.wavelengths), np.asarray(sd.values, np.float64)

        def fn(x):
            return _table(w_src, v_src, x, 20.0)
    else:
        if light.name not in colour.SDS_ILLUMINANTS and light.name not in colour.SDS_LIGHT_SOURCES:
            raise InputError(f"colour-science has no light {light.name!r}")
        # measured lamps continue past their table as the simulator's lights do (tungsten
        # by Planck, illuminant A by its formula), not flat from 690 / 780 nm
        fn = light_function(light.name)
    # the camera sees each band's Gaussian response, not the SPD at its centre (lines!)
    return relative_band_spd(fn, wl_key, fw_key, f"light {light.label!r}")


def light_spectrum(light: Light, wavelengths: np.ndarray, fwhm: np.ndarray | float | None = None) -> np.ndarray:
    """Relative SPD of ``light`` at ``wavelengths``, mean 1 over 400–700 nm; float64 ``(bands,)``.

    With ``fwhm`` (nm) each value is the mean over that band's Gaussian response.
    """
    from mehs.capture.scene import band_fwhm

    wl = np.asarray(wavelengths, np.float64).reshape(-1)
    fw = None if fwhm is None else tuple(band_fwhm(fwhm, wl).tolist())
    return _light_spd(light, tuple(wl.tolist()), fw)
