"""The noise model measured from a bracket with something moving in it.

Photon transfer compares consecutive exposures sample by sample; a moving object makes
them disagree by far more than noise. The 5σ clip of each signal level's samples kept
those of the moving patch's samples that stayed within 5σ, and the simulator's sensor
(gain 0.25 DN/e⁻) came out at 0.42–0.58 DN/e⁻. The truth here is the simulator's
sensor; the static scene is measured alongside.
"""

from __future__ import annotations

import numpy as np
import pytest

from mehs.capture.scene import SPECIM_IQ_WAVELENGTHS, make_scene
from mehs.capture.sensor import SensorModel
from mehs.capture.simulate import simulate_bracket
from mehs.cube import SpectralCube
from mehs.synthesis import _ptc_groups as G
from mehs.synthesis import _ptc_moving
from mehs.synthesis import noise as N
from mehs.synthesis.bracket import Bracket
from mehs.synthesis.fuse import estimate_noise
from mehs.synthesis.response import ResponseCurve


def _bracket(kind, motion, band_step, seed=1, size=48, times=(0.5, 2.0, 8.0)):
    wl = SPECIM_IQ_WAVELENGTHS[::band_step]
    sc = make_scene(kind, lines=size, samples=size, wavelengths=wl, seed=seed, motion=motion)
    sen = SensorModel(seed=seed)
    sim = simulate_bracket(sc, sen, list(times), seed=seed)
    b = Bracket([SpectralCube(e, sc.wavelengths) for e in sim.exposures], list(sim.darks),
                [None] * len(times), sim.times_ms, sc.wavelengths, bit_depth=12)
    return b, sen


def _noise(b):
    sat = np.full(b.shape[2], 0.98 * 4095, np.float32)
    model, info = estimate_noise(b, ResponseCurve.linear(12), sat)
    assert "fallback" not in info, info
    return model


@pytest.mark.parametrize("kind, band_step, seed", [("colorchecker", 1, 1), ("colorchecker", 4, 2),
                                                   ("ramp", 4, 1), ("lamp", 1, 2),
                                                   ("window", 4, 1)])
def test_a_moving_patch_leaves_the_gain_and_read_noise(kind, band_step, seed):
    b_static, sen = _bracket(kind, False, band_step, seed)
    b_moving, _ = _bracket(kind, True, band_step, seed)
    static, moving = _noise(b_static), _noise(b_moving)
    assert static.gain == pytest.approx(sen.gain_dn_per_e, rel=0.02)
    # before: 0.41–0.58 DN/e⁻
    assert moving.gain == pytest.approx(sen.gain_dn_per_e, rel=0.05)
    # read noise + quantisation + the dark reference (≈ 4.4 DN²), as without motion
    assert moving.read_noise == pytest.approx(static.read_noise, rel=0.02)


def test_the_moving_pixels_are_the_ones_dropped(monkeypatch):
    b, _ = _bracket("colorchecker", True, 4)
    probe = N.probe_bracket(b, np.full(b.shape[2], 0.98 * 4095, np.float32))
    scene = make_scene("colorchecker", lines=48, samples=48,
                       wavelengths=SPECIM_IQ_WAVELENGTHS[::4], seed=1, motion=True)
    found = []
    real = G._moving_pixels
    monkeypatch.setattr(G, "_moving_pixels", lambda *a: found.append(real(*a)) or found[-1])
    N._pair_groups_compute(probe, lambda raw, dark, j: raw - dark, 0, 1, N.PTC_GROUPS)
    moved = (scene.radiance_at(0) != scene.radiance_at(1)).any(axis=2)[probe.lines].ravel()
    assert found[0] is not None and found[0].sum() >= 20
    # a static pixel is never taken for one, but for the neighbours of a moved one (2 ·
    # RUN_HALF along the probe's pixels) that go with the runs around it
    # (_ptc_moving._moving_runs)
    h = 2 * _ptc_moving.RUN_HALF
    near = np.convolve(moved, np.ones(2 * h + 1), mode="same") > 0
    assert not (found[0] & ~near).any()
    assert found[0][moved].mean() > 0.8                 # most of the moved ones


def test_no_pixel_of_a_static_scene_is_dropped(monkeypatch):
    b, _ = _bracket("window", False, 1, seed=2)
    probe = N.probe_bracket(b, np.full(b.shape[2], 0.98 * 4095, np.float32))
    found = []
    real = G._moving_pixels
    monkeypatch.setattr(G, "_moving_pixels", lambda *a: found.append(real(*a)) or found[-1])
    N.estimate_noise_PTC(probe, lambda raw, dark, j: raw - dark)
    assert len(found) == 2 and all(f is None for f in found)


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_numpy_and_compiled_passes_agree_with_pixels_dropped(monkeypatch, dtype):
    """The compiled pass over the runs of kept pixels, the same over them copied
    together, and numpy's pass (while the compiled one builds) give the same bits."""
    from mehs.synthesis import _native

    b, _ = _bracket("ramp", True, 4)
    probe = N.probe_bracket(b, np.full(b.shape[2], 0.98 * 4095, np.float32))

    def lin(raw, dark, j):
        return (raw - dark).astype(dtype)

    dropped = []
    real = G._moving_pixels
    monkeypatch.setattr(G, "_moving_pixels", lambda *a: dropped.append(real(*a)) or dropped[-1])
    runs = N._pair_groups_compute(probe, lin, 0, 1, N.PTC_GROUPS)
    assert dropped[-1] is not None
    monkeypatch.setattr(G, "MAX_RUNS", 0)
    copied = N._pair_groups_compute(probe, lin, 0, 1, N.PTC_GROUPS)
    monkeypatch.setattr(_native, "building", lambda *a, **k: True)
    numpy_pass = N._pair_groups_compute(probe, lin, 0, 1, N.PTC_GROUPS)
    for k in runs:
        np.testing.assert_array_equal(np.asarray(copied[k]), np.asarray(runs[k]), err_msg=k)
        np.testing.assert_array_equal(np.asarray(numpy_pass[k]), np.asarray(runs[k]), err_msg=k)


@pytest.mark.parametrize("bands", [3, 8])
def test_a_moving_patch_seen_in_few_bands_leaves_the_gain(bands):
    """A pixel's own 3–8 samples see the patch's fringe (shifts of a few σ) too weakly;
    runs of neighbouring pixels see it. Before: 3 bands +29 … +76 %, 8 bands +17 …
    +24 % (256², the simulator's window scene)."""
    idx = np.unique(np.linspace(0, 203, bands).round().astype(int))
    wl = SPECIM_IQ_WAVELENGTHS[idx]
    for seed in (1, 2):
        sc = make_scene("window", lines=256, samples=256, wavelengths=wl, seed=seed,
                        motion=True)
        sen = SensorModel(seed=seed)
        sim = simulate_bracket(sc, sen, [0.5, 2.0, 8.0], seed=seed)
        b = Bracket([SpectralCube(e, wl) for e in sim.exposures], list(sim.darks),
                    [None] * 3, sim.times_ms, wl, bit_depth=12)
        assert _noise(b).gain == pytest.approx(sen.gain_dn_per_e, rel=0.04)
