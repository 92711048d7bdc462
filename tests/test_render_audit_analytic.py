"""Spectral IBL against analytic truth (independent of mehs's own formulas).

- A diffuse plane (albedo ρ) of normal ``n`` under a lat-long map reflects ``ρ/π · E(n)``,
  ``E = ∫ L(ω) max(0, n·ω) dω`` computed here by numpy quadrature over the map in Mitsuba's
  ``envmap`` layout (solid angle ``sin θ dθ dφ``), for normals facing the patch, away from it
  and sideways (orientation, mirroring), at two seeds and sample counts (unbiased).
- Thin films: Macleod's characteristic-matrix method (``N = n − ik``, admittances
  ``η_s = N cos θ``, ``η_p = N / cos θ``), written here, for 300 nm SiO₂ on Si and the
  paper's 5 nm Al + 400 nm SiO₂ on Si, at normal and oblique incidence, through the BSDF
  table Mitsuba actually samples.
"""

import math

import numpy as np
import pytest

mi = pytest.importorskip("mitsuba")

from mehs.render.maps import EnvMap  # noqa: E402
from mehs.render.materials import (TABLE_COS, TABLE_WAVELENGTHS, parse_material,  # noqa: E402
                                   refractive_index, spectral_table)
from mehs.render.plugins import plugin_classes  # noqa: E402
from mehs.rgb import WAVELENGTHS_31 as WL  # noqa: E402

H, W = 16, 32


def _patch_map() -> EnvMap:
    rad = np.full((H, W, WL.size), 0.05, np.float32)
    # an asymmetric bright patch: upper hemisphere, φ ≈ 60° (towards +x, −z)
    rad[4:6, 5:8] = 20.0 * np.linspace(0.5, 1.5, WL.size, dtype=np.float32)
    return EnvMap(rad, WL)


def _irradiance(env: EnvMap, n: np.ndarray, band: int) -> float:
    """``∫ L max(0, n·ω) dω`` by midpoint quadrature, the map read bilinearly as Mitsuba's
    ``envmap`` reads it (u = atan2(x, −z)/2π, v = acos(y)/π, rows at v = j/(H − 1))."""
    nt, npk = 400, 800
    th = (np.arange(nt) + 0.5) / nt * np.pi
    ph = (np.arange(npk) + 0.5) / npk * 2 * np.pi
    T, P = np.meshgrid(th, ph, indexing="ij")
    d = np.stack([np.sin(T) * np.sin(P), np.cos(T), -np.sin(T) * np.cos(P)], -1)
    x = P / (2 * np.pi) * W - 0.5
    x0 = np.floor(x).astype(int)
    fx = x - x0
    x0 %= W
    x1 = (x0 + 1) % W
    y = T / np.pi * (H - 1)
    y0 = np.minimum(y.astype(int), H - 2)
    fy = y - y0
    b = env.radiance[..., band].astype(np.float64)
    L = (1 - fy) * ((1 - fx) * b[y0, x0] + fx * b[y0, x1]) + fy * ((1 - fx) * b[y0 + 1, x0]
                                                                   + fx * b[y0 + 1, x1])
    cos = np.clip(d @ n, 0.0, None)
    return float((L * cos * np.sin(T)).sum() * (np.pi / nt) * (2 * np.pi / npk))


def _render_plane(env: EnvMap, n: np.ndarray, rho: float, lam: float, spp: int, seed: int) -> float:
    mi.set_variant("scalar_spectral")
    HSEnvmap, _ = plugin_classes("scalar_spectral")
    up = [0, 1, 0] if abs(n[1]) < 0.9 else [0, 0, 1]
    look = mi.ScalarTransform4f().look_at
    scene = mi.load_dict({
        "type": "scene", "integrator": {"type": "path", "max_depth": 2},
        "sensor": {"type": "perspective", "fov": 5, "to_world": look(origin=(3 * n).tolist(),
                                                                       target=[0, 0, 0], up=up),
                   "sampler": {"type": "independent", "sample_count": spp},
                   "film": {"type": "specfilm", "width": 4, "height": 4, "rfilter": {"type": "box"},
                            "b0": {"type": "irregular", "wavelengths": f"{lam - 0.1}, {lam + 0.1}",
                                   "values": "1, 1"}}},
        # a rectangle's normal is its local +z; look_at sends +z towards the target
        "plane": {"type": "rectangle", "to_world": look(origin=[0, 0, 0], target=n.tolist(), up=up),
                  "bsdf": {"type": "diffuse", "reflectance": {"type": "spectrum", "value": rho}}},
        "light": HSEnvmap(mi.Properties(), envmap=env)})
    return float(np.mean(np.array(mi.render(scene, spp=spp, seed=seed))) / 0.2)


@pytest.mark.parametrize("normal", [(0, 1, 0), (1, 0, 0), (-1, 0, 0), (0, 0, -1), (0, 0, 1)])
def test_diffuse_plane_under_a_patch_reflects_rho_over_pi_times_irradiance(normal):
    env = _patch_map()
    n = np.asarray(normal, dtype=np.float64)
    band = 15                                   # 550 nm, a map band centre
    expect = 0.5 / math.pi * _irradiance(env, n, band)
    got = [_render_plane(env, n, 0.5, float(WL[band]), spp, seed) for spp, seed in ((256, 1), (512, 2))]
    # two independent estimates agree with the quadrature (and so with each other)
    assert got == pytest.approx([expect, expect], rel=0.03), (normal, got, expect)


def _macleod_R(stack, lam: np.ndarray, cos0: float) -> np.ndarray:
    """Unpolarised reflectance by the characteristic-matrix method (Macleod, Thin-Film
    Optical Filters §2), ``N = n − ik`` (the conjugate of the ``n + ik`` tables)."""
    ns = ([np.ones_like(lam, dtype=complex)] + [np.conj(refractive_index(m, lam)) for m, _ in stack.layers]
          + [np.conj(refractive_index(stack.substrate, lam))])
    s0 = math.sqrt(1.0 - cos0 ** 2)
    out = []
    for pol in "sp":
        def cos(N):
            c = np.sqrt(1 - (s0 / N) ** 2 + 0j)
            return np.where((N * c).imag > 0, -c, c)     # decaying branch for n − ik

        def eta(N):
            return N * cos(N) if pol == "s" else N / cos(N)
        m11, m12, m21, m22 = (np.ones_like(lam, complex), np.zeros_like(lam, complex),
                              np.zeros_like(lam, complex), np.ones_like(lam, complex))
        for N, (_, d) in zip(ns[1:-1], stack.layers):
            dl = 2 * np.pi * N * cos(N) * d / lam
            e = eta(N)
            a11, a12, a21, a22 = np.cos(dl), 1j * np.sin(dl) / e, 1j * e * np.sin(dl), np.cos(dl)
            m11, m12, m21, m22 = (m11 * a11 + m12 * a21, m11 * a12 + m12 * a22,
                                  m21 * a11 + m22 * a21, m21 * a12 + m22 * a22)
        es, e0 = eta(ns[-1]), eta(ns[0])
        B, C = m11 + m12 * es, m21 + m22 * es
        out.append(np.abs((e0 * B - C) / (e0 * B + C)) ** 2)
    return 0.5 * (out[0] + out[1])


@pytest.mark.parametrize("spec", ["thin-film:SiO2:300nm", "thin-film:Al:5nm,SiO2:400nm"])
def test_thin_film_bsdf_matches_an_independent_characteristic_matrix(spec):
    _, stack = parse_material(spec)
    lam = np.arange(400.0, 701.0, 10.0)
    for c in (1.0, 0.7, 0.3):
        np.testing.assert_allclose(stack.reflectance(lam, np.array([c]))[:, 0],
                                   _macleod_R(stack, lam, c), atol=1e-12)
    # what Mitsuba samples: the BSDF plugin's table look-up, off the table's nodes
    mi.set_variant("scalar_spectral")
    _, ThinFilm = plugin_classes("scalar_spectral")
    bsdf = ThinFilm(mi.Properties(), table=spectral_table(stack), cos_theta=TABLE_COS,
                    wavelengths=TABLE_WAVELENGTHS)
    rng = np.random.default_rng(7)
    for c in rng.uniform(0.05, 1.0, 40):
        lams = rng.uniform(400.0, 700.0, 4)
        si = mi.SurfaceInteraction3f()
        si.wi = mi.Vector3f(math.sqrt(1 - c * c), 0.0, c)
        si.wavelengths = mi.Spectrum(*lams)
        bs, w = bsdf.sample(mi.BSDFContext(), si, 0.5, mi.Point2f(0.5, 0.5))
        got = np.array([w[i] for i in range(4)])
        np.testing.assert_allclose(got, _macleod_R(stack, lams, float(si.wi[2])), atol=3e-3)
        assert float(bs.wo[2]) == pytest.approx(float(si.wi[2]), abs=1e-6)   # mirror
