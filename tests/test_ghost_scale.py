"""Ghost detection against the simulator's truth: the χ² scale under a wrong noise model,
the false-alarm rate of static scenes, recall on a moving one, and bad input."""

import dataclasses

import numpy as np
import pytest

from mehs.capture.scene import SPECIM_IQ_WAVELENGTHS, make_scene
from mehs.capture.sensor import SensorModel
from mehs.capture.simulate import simulate_bracket
from mehs.errors import InputError
from mehs.synthesis.ghost import deghost_from_reference, detect_ghosts
from mehs.synthesis.merge import NoiseModel, merge_bracket


def _merge(kind="colorchecker", n=32, bands=16, times=(1.0, 4.0, 16.0), motion=False,
           seed=1, gain=1.0, read=1.0, noise=None):
    """Simulate and merge; the noise model is the simulator's own sensor (read noise,
    quantisation, dark current in DN) with gain and read noise scaled by ``gain``, ``read``."""
    wl = SPECIM_IQ_WAVELENGTHS[::max(1, 204 // bands)][:bands]
    scene = make_scene(kind, lines=n, samples=n, seed=seed, wavelengths=wl, motion=motion)
    sen = SensorModel(seed=seed)
    sim = simulate_bracket(scene, sen, times, seed=seed, white=False)
    if noise is None:
        g = sen.gain_dn_per_e
        true = NoiseModel(gain=g, read_noise=float(np.hypot(sen.read_noise_e * g, np.sqrt(1 / 12))),
                          relative=0.0, dark_current=sen.dark_current_e_per_ms * g)
        noise = dataclasses.replace(true, gain=true.gain * gain, read_noise=true.read_noise * read)
    mr = merge_bracket(sim.exposures, sim.times_ms, darks=sim.darks, bit_depth=12, noise=noise,
                       saturation=np.float32(0.98 * 4095))
    return mr, scene.moved_mask(len(times))


@pytest.mark.parametrize("read", [14.0, 2.0])
@pytest.mark.parametrize("scale", ["auto", "level"])
@pytest.mark.parametrize("kind", ["colorchecker", "lamp"])
def test_an_overstated_read_noise_does_not_flag_a_static_frame(kind, scale, read):
    """A read noise set too high shrinks the χ² of dark samples only; the frame's median
    (dark) pixel then set a scale of 0.01 (×14) / 0.4 (×2) that divided the χ² of every
    shot-noise-limited pixel up: 15–17 % (×14) and 0.7–2 % (×2) of this static frame
    flagged ("auto"), 2.5–3 % with the per-level scale (×14), whose median scale was 0.4
    at ×2. Overstated noise must mean fewer ghosts."""
    mr, _ = _merge(kind, read=read)
    has = mr.dof > 0
    g = detect_ghosts(mr.chi2, mr.dof, alpha=1e-4, scale=scale, level=mr.mean_radiance,
                      min_pixels=1, grow=0)
    assert g.mask[has].mean() <= 0.002, (g.mask[has].mean(), g.scale)
    assert g.scale >= 1.0
    # the overstatement is still reported
    assert g.fit < (0.05 if read > 10 else 0.6), g.fit


def test_an_understated_noise_model_is_still_divided_out():
    """Gain ×0.5 (noise understated): χ² runs 1.3× high at every pixel; the scale takes it out."""
    mr, _ = _merge("ramp", gain=0.5)
    has = mr.dof > 0
    g = detect_ghosts(mr.chi2, mr.dof, alpha=1e-4, min_pixels=1, grow=0)
    assert g.scale == pytest.approx(g.fit) and 1.15 < g.scale < 1.6
    assert g.mask[has].mean() <= 0.005
    raw = detect_ghosts(mr.chi2, mr.dof, alpha=1e-4, scale=1.0, min_pixels=1, grow=0)
    assert raw.mask[has].mean() > g.mask[has].mean()


@pytest.mark.parametrize("kind,bands,times", [
    ("colorchecker", 3, (1.0, 8.0)),
    ("lamp", 5, (1.0, 4.0, 16.0)),
    ("window", 17, (1.0, 8.0)),
    ("ramp", 17, (1.0, 4.0, 16.0)),
])
def test_the_false_alarm_rate_of_a_static_scene_is_about_alpha(kind, bands, times):
    """Before the clean-up (min_pixels 1, no growth), with the simulator's noise model:
    the rate of flagged static pixels at α = 0.01 is α (2304 pixels: 23 ± 5 expected)."""
    mr, _ = _merge(kind, n=48, bands=bands, times=times)
    has = mr.dof > 0
    g = detect_ghosts(mr.chi2, mr.dof, alpha=1e-2, min_pixels=1, grow=0)
    assert 0.004 <= g.mask[has].mean() <= 0.02, g.mask[has].mean()
    # the defaults (α = 1e-4, groups of 3, grown by 1) leave a static frame clean
    assert detect_ghosts(mr.chi2, mr.dof).fraction == 0.0


def test_a_moving_patch_is_found_with_good_recall_and_precision():
    mr, moved = _merge("colorchecker", n=48, motion=True)
    raw = detect_ghosts(mr.chi2, mr.dof, min_pixels=1, grow=0)
    assert raw.mask[moved].mean() >= 0.8           # recall (the soft rim moves < 1σ)
    assert not raw.mask[~moved].any()              # no static pixel flagged
    g = detect_ghosts(mr.chi2, mr.dof)
    assert (g.mask & moved).sum() / g.mask.sum() >= 0.8      # precision after the growth


def test_pixels_without_dof_are_never_flagged():
    rng = np.random.default_rng(0)
    dof = np.full((16, 16), 8, np.int32)
    dof[:, :4] = 0
    chi2 = rng.chisquare(8, dof.shape).astype(np.float32)
    chi2[:, :4] = 1e9                   # whatever the merge left there
    g = detect_ghosts(chi2, dof, min_pixels=1, grow=0)
    assert not g.mask[:, :4].any() and np.all(g.score[:, :4] == 0)
    none = detect_ghosts(chi2, np.zeros_like(dof))
    assert none.fraction == 0.0 and none.scale == 1.0 and np.isnan(none.fit)


def test_bad_input_is_refused_with_a_clear_message():
    rng = np.random.default_rng(0)
    dof = np.full((16, 16), 8, np.int32)
    chi2 = rng.chisquare(8, dof.shape)
    bad = chi2.copy()
    bad[3, 3] = np.nan                  # made the frame's scale silently 1
    with pytest.raises(InputError, match="NaN"):
        detect_ghosts(bad, dof)
    with pytest.raises(InputError, match="'auto', 'level'"):
        detect_ghosts(chi2, dof, scale="levels")       # was float('levels')' ValueError
    lev = rng.uniform(1, 10, dof.shape)
    lev[0, 0] = np.nan
    with pytest.raises(InputError, match="finite level"):
        detect_ghosts(chi2, dof, scale="level", level=lev)


def test_deghost_checks_the_reference_even_without_ghosts():
    """A frame without ghost pixels returned any reference index unchecked (into the summary)."""
    stack = [np.zeros((2, 2, 1), np.uint16)] * 3
    args = dict(linearise=lambda r, d, j: r - d, saturation=np.array([4000.0]), floor=0.0,
                calibration=np.ones(1))
    empty = np.zeros((2, 2), bool)
    with pytest.raises(InputError, match="0..2"):
        deghost_from_reference(np.zeros((2, 2, 1), np.float32), empty, stack, [None] * 3,
                               np.array([1.0, 4.0, 16.0]), reference=7, **args)
    assert deghost_from_reference(np.zeros((2, 2, 1), np.float32), empty, stack, [None] * 3,
                                  np.array([1.0, 4.0, 16.0]), reference=2, **args) == 2


def test_fuse_with_a_read_noise_twice_too_high_reports_no_ghosts():
    """End to end, 204 bands: a read noise ×2 (as a user's noise model may have) made
    `fuse_bracket` report this static frame 42 % ghost (48 px: 36 %; ×14: 52 %)."""
    from mehs.cube import SpectralCube
    from mehs.synthesis.bracket import Bracket
    from mehs.synthesis.fuse import fuse_bracket

    wl = SPECIM_IQ_WAVELENGTHS
    sen = SensorModel(seed=1)
    sim = simulate_bracket(make_scene("colorchecker", lines=24, samples=24, seed=1, wavelengths=wl),
                           sen, (1.0, 4.0, 16.0), seed=1, white=False)
    br = Bracket([SpectralCube(e, wl) for e in sim.exposures], sim.darks, [None] * 3,
                 sim.times_ms, wl, bit_depth=12)
    g = sen.gain_dn_per_e
    read = 2 * float(np.hypot(sen.read_noise_e * g, np.sqrt(1 / 12)))
    r = fuse_bracket(br, response="linear", noise=NoiseModel(
        gain=g, read_noise=read, relative=0.0, dark_current=sen.dark_current_e_per_ms * g))
    assert r.summary["ghost_fraction"] == 0.0
    assert r.summary["ghost_chi2_scale"] == 1.0
