"""Spectral diversity on signed, noisy HDR cubes: the truth is the simulator's radiance.

A fused 48×48 ColorChecker (with its lamp) at 10⁻³ of its light gave 2279 "distinct
spectra" in 2304 pixels at 4° (the truth: 25) and a 77° median angle to the nearest
training pixel (truth: 0°); clipping the negatives gave 51°; at full light 211 and 1.6°.
Pixels below the noise are now excluded and counted. And the pixels were read in raster
order: of a 128×128 cube the clustering saw the top 64 lines only.
"""

from __future__ import annotations

import numpy as np
import pytest

from mehs.capture.scene import make_scene
from mehs.capture.sensor import SensorModel
from mehs.capture.simulate import simulate_bracket
from mehs.cube import SpectralCube
from mehs.errors import InputError
from mehs.rgb import WAVELENGTHS_31
from mehs.scenes.diversity import (draw, figures, format_diversity, screen_cube,
                                   spectral_diversity)
from mehs.synthesis.bracket import Bracket
from mehs.synthesis.fuse import fuse_bracket

WL = WAVELENGTHS_31
TIMES = (0.05, 0.5, 5.0, 50.0)


@pytest.fixture(scope="module")
def chart():
    """Truth (in the fused cube's DN/ms direction) and a training truth of another seed."""
    scale = SensorModel(seed=1).signal_scale(WL.size, WL)
    sc = make_scene("colorchecker", lines=48, samples=48, wavelengths=WL, seed=1)
    ref = make_scene("colorchecker", lines=48, samples=48, wavelengths=WL, seed=2)
    return sc, sc.radiance * scale, ref.radiance * scale


def _fused(scene, level):
    sen = SensorModel(seed=1, radiance_to_e_per_ms=400.0 * level)
    sim = simulate_bracket(scene, sen, list(TIMES), seed=1)
    b = Bracket([SpectralCube(e, WL) for e in sim.exposures], sim.darks, [None] * len(TIMES),
                sim.times_ms, WL, bit_depth=12)
    r = fuse_bracket(b, response="linear", ghosts="off")
    return np.asarray(r.radiance.data, dtype=np.float64), r.mask == 0


@pytest.mark.parametrize("level", [1.0, 1e-1, 1e-3])
def test_statistics_agree_with_the_truth_at_every_light_level(chart, level):
    scene, truth, ref = chart
    x, valid = _fused(scene, level)
    excluded = []
    for cube in (x, np.clip(x, 0, None)):            # signed and clipped
        d = spectral_diversity(cube, ref, angle_deg=4.0, valid=valid)
        assert d["noise_angle_deg"] == 2.0 and d["noise_source"] == ["neighbours"]
        assert d["pixels"] > 20 and d["pixels_total"] == 48 * 48
        excluded.append(d["excluded_noise_fraction"])
        # the same pixels of the noise-free truth
        _, keep, _ = screen_cube(cube, valid=valid, noise_angle_deg=2.0)
        t = figures(draw([(truth.reshape(-1, WL.size), keep)], None, np.random.default_rng(0)),
                    None, 4.0)
        # 27 / 25, 4 / 3, 1 / 1 (before: 211, 1782, 2279)
        assert abs(d["distinct_spectra"] - t["distinct_spectra"]) <= 3, (d, t)
        # the training truth holds every kept spectrum: the angle left is the noise
        assert d["nn_angle_median"] < 2.0 and d["nn_angle_p90"] < 2.5, d
        # the kept pixels really lie within the noise angle of the truth
        kx, kt = cube.reshape(-1, WL.size)[keep], truth.reshape(-1, WL.size)[keep]
        cos = (kx * kt).sum(1) / np.linalg.norm(kx, axis=1) / np.linalg.norm(kt, axis=1)
        assert np.percentile(np.degrees(np.arccos(np.clip(cos, -1, 1))), 95) < 2.5
    # the dimmer, the more is below the noise; signed and clipped alike
    assert excluded[0] == pytest.approx(excluded[1], abs=0.01)
    lo, hi = {1.0: (0.3, 0.6), 1e-1: (0.8, 0.97), 1e-3: (0.97, 1.0)}[level]   # 0.43 0.91 0.99
    assert lo <= excluded[0] <= hi


def test_noise_free_truth_loses_no_pixel_and_pure_noise_keeps_none(chart):
    _, truth, _ = chart
    d = spectral_diversity(truth, angle_deg=4.0)
    assert d["excluded_noise"] == 0 and d["excluded_invalid"] == 0
    assert d["noise_angle_median"][0] < 0.01
    noise = np.random.default_rng(3).normal(0.0, 1.0, (32, 32, WL.size))
    for cube in (noise, np.clip(noise, 0, None)):
        d = spectral_diversity(cube, noise + 5.0)
        assert d["pixels"] == 0 and d["excluded_noise"] == 32 * 32
        assert d["distinct_spectra"] is None and d["nn_angle_median"] is None
        text = format_diversity(d)
        assert "1024 (100.0%)" in text and "n/a (no pixel left)" in text
        # and says what to change: an angle above the measured noise
        hint = next(line for line in text.splitlines() if line.startswith("hint"))
        wanted = 2 * max(d["noise_angle_median"])
        assert "--angle" in hint and f"{wanted:.2g}°" in hint


def test_pixels_are_drawn_from_the_whole_cube_not_its_first_lines():
    # before: a 128×128 cube (≤ sample pixels) was read in raster order and only its first
    # 8192 pixels (the top half) clustered: 1 distinct spectrum, 0° to a reference holding
    # the top half's spectrum only
    a = np.exp(-((WL - 450.0) / 40.0) ** 2) + 0.1
    b = np.exp(-((WL - 620.0) / 40.0) ** 2) + 0.1
    cube = np.empty((128, 128, WL.size))
    cube[:64], cube[64:] = a, b
    ab = np.degrees(np.arccos(a @ b / np.linalg.norm(a) / np.linalg.norm(b)))
    d = spectral_diversity(cube, np.broadcast_to(a, (8, 8, WL.size)))
    assert d["distinct_spectra"] == 2
    assert d["nn_angle_p90"] == pytest.approx(ab, rel=1e-6)
    assert d["excluded_noise"] == 0


def test_rows_without_layout_are_used_whole_and_say_so():
    rows = np.random.default_rng(0).uniform(0.1, 1.0, (500, WL.size))
    d = spectral_diversity(rows)
    assert d["pixels"] == 500 and d["excluded_noise"] == 0
    assert d["noise_source"] == ["not measured: no spatial layout (pixel rows)"]
    assert "not measured" in format_diversity(d)


def test_min_norm_override_masks_and_bad_arguments(chart):
    _, truth, _ = chart
    norms = np.linalg.norm(truth, axis=-1)
    thr = float(np.median(norms))
    d = spectral_diversity(truth, min_norm=thr)
    assert d["excluded_noise"] == int(np.count_nonzero(norms < thr))
    assert d["noise_source"] == ["given: min_norm"]
    valid = np.ones(truth.shape[:2], bool)
    valid[:10] = False
    d = spectral_diversity(truth, valid=valid, min_norm=0)
    assert d["excluded_invalid"] == 10 * 48 and d["excluded_noise"] == 0
    with pytest.raises(InputError, match="noise_angle_deg"):
        spectral_diversity(truth, noise_angle_deg=0)
    with pytest.raises(InputError, match="angle_deg"):
        spectral_diversity(truth, angle_deg=-1)
    with pytest.raises(InputError, match="min_norm"):
        spectral_diversity(truth, min_norm=-1.0)
    with pytest.raises(InputError, match="2 masks for 1 cubes"):
        spectral_diversity(truth, valid=[valid, valid])
    with pytest.raises(InputError, match="finite, non-zero"):
        spectral_diversity(np.zeros((8, 8, 3)))
