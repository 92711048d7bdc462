"""Audit of the render step against independent truths (colour-science, analytic cases)."""

import numpy as np
import pytest

from mehs.errors import InputError
from mehs.render.maps import EnvMap, map_weights, rgb_map

# a Specim IQ's 204 band centres run 397–1004 nm, past the CIE tables' 830 nm
SPECIM_WL = np.linspace(397.32, 1003.58, 204)


def _smooth(lam):
    return 1.0 + 0.6 * np.sin(lam / 40.0) + 0.002 * (lam - 400.0)


def test_map_with_nir_bands_gets_its_colour_from_the_visible_bands():
    import colour

    from mehs.rgb import XYZ_to_linear_sRGB

    env = EnvMap(np.broadcast_to(_smooth(SPECIM_WL).astype(np.float32), (3, 4, 204)).copy(),
                 SPECIM_WL, "specim.hdr")
    ours = rgb_map(env)[0, 0]
    # colour-science: the same spectrum at 1 nm over the whole CIE table, equal-energy
    # weighting, then the same XYZ → linear-sRGB matrix
    lam = np.arange(360.0, 831.0)
    sd = colour.SpectralDistribution(dict(zip(lam, _smooth(lam))))
    flat = colour.SpectralDistribution(dict(zip(lam, np.ones_like(lam))))
    cmfs = colour.MSDS_CMFS["CIE 1931 2 Degree Standard Observer"]
    XYZ = np.asarray(colour.sd_to_XYZ(sd, cmfs, flat, method="Integration")) / 100.0
    ref = XYZ_to_linear_sRGB(XYZ, clip_negative=False)
    # the map has no band below 397 nm: blue loses its 360–397 nm tail (~0.6 %)
    assert ours == pytest.approx(ref, rel=0.01)
    w = map_weights(env)
    assert w.shape == (3, 4) and np.all(w > 0)


def test_map_with_no_visible_bands_is_refused_naming_it():
    wl = np.linspace(850.0, 1000.0, 16)
    env = EnvMap(np.ones((3, 4, wl.size), np.float32), wl, "nir_only.hdr")
    with pytest.raises(InputError, match="visible") as exc:
        rgb_map(env)
    assert "nir_only.hdr" in str(exc.value)


def _open_box_obj(path, a):
    """An open box (no −z face) of half-size ``a``, faces towards its inside."""
    v = [(-a, -a, -a), (a, -a, -a), (a, a, -a), (-a, a, -a),
         (-a, -a, a), (a, -a, a), (a, a, a), (-a, a, a)]
    faces = [(5, 7, 6), (5, 8, 7), (1, 8, 5), (1, 4, 8), (2, 7, 3), (2, 6, 7),
             (4, 7, 8), (4, 3, 7), (1, 6, 2), (1, 5, 6)]
    path.write_text("".join(f"v {x} {y} {z}\n" for x, y, z in v)
                    + "".join(f"f {i} {j} {k}\n" for i, j, k in faces))
    return path


def test_hs_render_of_a_mesh_is_scale_invariant_and_shadows_like_mitsuba(tmp_path):
    pytest.importorskip("mitsuba")
    from mehs.render.maps import uniform_map
    from mehs.render.scene import RenderSettings, render_rgb, render_spectral
    from mehs.rgb import WAVELENGTHS_31, hdr_rgb

    env = uniform_map(np.ones(WAVELENGTHS_31.size), WAVELENGTHS_31)
    bands = tuple(float(b) for b in WAVELENGTHS_31[::3])
    centre = {}
    for a in (0.5, 5.0):
        s = RenderSettings(width=16, height=16, spp=64, material="diffuse:0.8", bands=bands,
                           object=str(_open_box_obj(tmp_path / f"box{a:g}.obj", a)))
        # the camera looks into the box through its opening: the back wall's centre
        centre[a] = hdr_rgb(render_spectral(s, hs_map=env), bands)[5:11, 5:11].mean((0, 1))
    # the same seed on a scaled copy of the scene traces scaled copies of the same paths:
    # only the walls' shadowing can tell the two apart (29 % more light leaked at a = 5)
    assert centre[5.0] == pytest.approx(centre[0.5], rel=0.02)
    # Mitsuba's own envmap (RGB renderer) with the map's RGB shadows the big box the same
    # (to the spectral film's colour noise, ~3 % here)
    stock = render_rgb(s, rgb_map(env))[5:11, 5:11].mean((0, 1))
    assert centre[5.0].sum() == pytest.approx(stock.sum(), rel=0.06)
