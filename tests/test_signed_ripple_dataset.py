"""Dataset figures of fused cubes that keep negative (signed, unbiased) estimates.

Since the merge keeps its signed estimate, dark pixels of a fused cube hold noise around
zero; these tests compare the dataset build's figures on such cubes with the simulator's
own radiance.
"""

import numpy as np
import pytest

from mehs.capture.scene import make_scene
from mehs.capture.sensor import SensorModel
from mehs.capture.simulate import simulate_bracket, write_simulated_scene
from mehs.synthesis.bracket import load_bracket
from mehs.synthesis.fuse import fuse_bracket
from mehs.synthesis.response import ResponseCurve


def _dim(tmp, factor):
    sc = make_scene("colorchecker", 24, 24, seed=1)
    sc.radiance = sc.radiance * np.float32(factor)
    sc.white_radiance = sc.white_radiance * np.float32(factor)
    sim = simulate_bracket(sc, SensorModel(seed=3), (0.04, 2.56, 163.84))
    folder = write_simulated_scene(sim, tmp / f"s{factor:g}", overwrite=True)
    truth = np.asarray(sim.truth, np.float32) * np.float32(sim.truth_dn_per_ms)
    return folder, truth


@pytest.fixture(scope="module")
def dim_cubes(tmp_path_factory):
    """ENVI cubes fused signed and clipped from a colorchecker at 1e-4 of normal light,
    and the dynamic range of the simulator's radiance (stops, computed here)."""
    from mehs.io.envi_write import write_envi
    from mehs.rgb import WAVELENGTHS_31, hdr_rgb, luminance
    from mehs.synthesis.resample import resample_cube

    tmp = tmp_path_factory.mktemp("dimcubes")
    folder, truth = _dim(tmp, 1e-4)
    out = {}
    for clip in (False, True):
        res = fuse_bracket(load_bracket(folder), response=ResponseCurve.linear(12),
                           ghosts="off", check_response=False, clip_negative=clip)
        out[clip] = write_envi(tmp / f"cube_{'clipped' if clip else 'signed'}.hdr",
                               res.radiance)
    assert res.radiance.data.shape == truth.shape
    t31 = resample_cube(res.radiance.with_data(truth), WAVELENGTHS_31).data
    y = luminance(hdr_rgb(t31, WAVELENGTHS_31))
    lo, hi = np.percentile(y[y > 0], [0.1, 99.9])
    return out, float(np.log2(hi / lo)), tmp


def test_dynamic_range_of_a_signed_dark_cube_is_noise_limited(dim_cubes):
    from mehs.dataset.build import build_from_hs

    cubes, truth_dr, tmp = dim_cubes
    m = build_from_hs([cubes[False], cubes[True]], tmp / "ds", workers=1, progress=False)
    q = {s["id"]: s["quality"] for s in m["scenes"]}
    signed = q["cube_signed"]["dynamic_range_stops"]
    clipped = q["cube_clipped"]["dynamic_range_stops"]
    # the simulator's radiance spans ~14.8 stops; the noisy cube cannot show more
    # (the old figure: 18.4 stops, the 0.1th percentile fell among noise samples near 0)
    assert 14 < truth_dr < 16
    assert signed < truth_dr
    # and it agrees with the same bracket clipped in the merge within a stop
    assert abs(signed - clipped) < 1.0


def test_dynamic_range_unchanged_without_negative_luminance():
    from mehs.dataset.scene_build import dynamic_range_stops

    rng = np.random.default_rng(0)
    rgb = rng.uniform(0.001, 10.0, (40, 40, 3)).astype(np.float32)
    from mehs.rgb import luminance

    y = luminance(rgb)
    assert dynamic_range_stops(rgb, signed_luminance=y) == dynamic_range_stops(rgb)
    lo, hi = np.percentile(y, [0.1, 99.9])
    assert dynamic_range_stops(rgb) == pytest.approx(np.log2(hi / lo))


def test_dynamic_range_of_pure_noise_is_not_high():
    """Zero radiance plus symmetric noise: no dynamic range (the old rule gave many stops)."""
    from mehs.dataset.scene_build import dynamic_range_stops

    rng = np.random.default_rng(1)
    y = rng.normal(0.0, 1.0, (200, 200))
    rgb = np.repeat(np.maximum(y, 0)[..., None], 3, axis=2).astype(np.float32)
    assert dynamic_range_stops(rgb) > 10            # the noise's positive half
    assert dynamic_range_stops(rgb, signed_luminance=y) < 1.0


def test_report_draws_a_dark_signed_spectrum_whole(dim_cubes, tmp_path, monkeypatch):
    """The darkest example spectrum (noise around 0) was drawn on a log axis with its
    negative samples as gaps; it is drawn whole on a symmetric log axis now."""
    from mehs.dataset import report
    from mehs.dataset.build import build_from_hs
    from mehs.io.envi import read_envi

    cubes, _, _ = dim_cubes
    ds = tmp_path / "ds"
    build_from_hs([cubes[False]], ds, workers=1, progress=False)
    figs = []
    monkeypatch.setattr(report, "_save", lambda fig, out: figs.append(fig))
    report.write_dataset_report(ds)
    ax = figs[0].axes[5]
    assert ax.get_title().startswith("example spectra")
    hs = read_envi(ds / "scenes" / "cube_signed" / "hs.hdr").data
    assert (hs < 0).any()
    lines = ax.get_lines()
    ys = [np.asarray(ln.get_ydata(), float) for ln in lines if ln.get_label().startswith("(")]
    assert len(ys) == 5
    for y in ys:
        assert np.isfinite(y).all()                 # no gaps
    assert (np.concatenate(ys) < 0).any()
    assert ax.get_yscale() == "symlog"
    # each plotted line is the cube's spectrum at the pixel its label names
    for ln, y in zip([ln for ln in lines if ln.get_label().startswith("(")], ys):
        r, c = (int(t.split()[-1]) for t in ln.get_label().strip("()").split(","))
        np.testing.assert_allclose(y, hs[r, c, :], rtol=1e-6)
