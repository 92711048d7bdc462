"""Simulated scene, sensor and bracket: physics and determinism."""

import json

import numpy as np
import pytest

from mehs.capture.scene import SPECIM_IQ_WAVELENGTHS, make_scene
from mehs.capture.sensor import SensorModel
from mehs.capture.simulate import simulate_bracket, write_simulated_scene
from mehs.errors import InputError

VIS = (SPECIM_IQ_WAVELENGTHS >= 400) & (SPECIM_IQ_WAVELENGTHS <= 700)


def test_specim_grid():
    wl = SPECIM_IQ_WAVELENGTHS
    assert wl.size == 204 and wl[0] == pytest.approx(397.32) and wl[-1] == pytest.approx(1003.58)
    d = np.diff(wl)
    assert d.min() > 2.85 and d.max() < 3.12
    assert VIS.sum() == 103
    # Specim IQ default bands {70,53,19} (1-based) sit at 598.6/548.6/449.4 nm.
    np.testing.assert_allclose(wl[[69, 52, 18]], [598.6, 548.6, 449.4], atol=0.1)


@pytest.mark.parametrize("kind", ["colorchecker", "lamp", "window", "ramp"])
def test_scene_is_hdr_and_finite(kind):
    s = make_scene(kind, lines=48, samples=48)
    assert s.radiance.dtype == np.float32 and s.radiance.shape == (48, 48, 204)
    assert np.isfinite(s.radiance).all() and (s.radiance >= 0).all()
    white = s.white_radiance[VIS].mean()
    lum = s.radiance[..., VIS].mean(axis=2)
    # a directly visible source 100–10 000× brighter than the diffuse white
    assert lum.max() >= 100 * white
    assert lum.max() <= 10_000 * white
    # and dark patches well below the white
    assert np.percentile(lum, 5) < 0.1 * white


def test_scene_light_source_spectrum_is_the_lamp():
    s = make_scene("lamp", lines=48, samples=48)
    lum = s.radiance[..., VIS].mean(axis=2)
    peak = np.unravel_index(np.argmax(lum), lum.shape)
    spec = s.radiance[peak]
    # high-pressure sodium: the emission near 589 nm dominates the blue
    assert spec[s_idx(589)] > 5 * spec[s_idx(450)]


def s_idx(nm):
    return int(np.argmin(np.abs(SPECIM_IQ_WAVELENGTHS - nm)))


def test_scene_deterministic_and_seeded():
    a, b = make_scene(seed=3), make_scene(seed=3)
    np.testing.assert_array_equal(a.radiance, b.radiance)
    c = make_scene(seed=4)
    assert not np.array_equal(a.radiance, c.radiance)


def test_motion_mask_only_with_motion():
    still = make_scene(lines=40, samples=40)
    assert not still.moved_mask().any()
    np.testing.assert_array_equal(still.radiance_at(2), still.radiance)
    moving = make_scene(lines=40, samples=40, motion=True)
    m = moving.moved_mask(3)
    assert 0 < m.mean() < 0.5
    diff = np.abs(moving.radiance_at(2) - moving.radiance_at(0)).max(axis=2)
    ref = moving.radiance_at(0).max(axis=2)
    assert (diff[m] > 0).all()
    assert (diff[~m] <= 1e-3 * ref[~m]).all()
    assert (diff[~m] == 0).mean() > 0.9


def test_bad_scene_args():
    with pytest.raises(InputError):
        make_scene("nope")
    with pytest.raises(InputError):
        make_scene(illuminant="XYZ123")


def test_expose_equals_stacked_lines_and_is_deterministic():
    s = make_scene(lines=12, samples=16)
    sen = SensorModel(seed=7)
    cube = sen.expose(s.radiance, 3.0, exposure_seed=11, line_offset=5)
    lines = np.stack([sen.expose_line(s.radiance[i], 3.0, exposure_seed=11, line_index=5 + i)
                      for i in range(12)])
    assert cube.dtype == np.uint16
    np.testing.assert_array_equal(cube, lines)
    np.testing.assert_array_equal(cube, SensorModel(seed=7).expose(s.radiance, 3.0, exposure_seed=11,
                                                                   line_offset=5))
    assert not np.array_equal(cube, SensorModel(seed=8).expose(s.radiance, 3.0, exposure_seed=11,
                                                               line_offset=5))


def test_signal_linear_in_time_and_dark_proportional():
    sen = SensorModel(column_fpn_sigma=0.0)
    rad = np.full((64, 32, 204), 0.2, dtype=np.float32)
    means = []
    for t in (5.0, 10.0, 20.0):
        z = sen.expose(rad, t, exposure_seed=1).astype(np.float64)
        means.append(z[..., VIS].mean() - sen.black_level_dn - sen.dark_current_e_per_ms * t * sen.gain_dn_per_e)
    assert means[1] / means[0] == pytest.approx(2.0, rel=0.01)
    assert means[2] / means[0] == pytest.approx(4.0, rel=0.01)
    zero = np.zeros((64, 32, 204), dtype=np.float32)
    darks = [sen.expose(zero, t, exposure_seed=2, shutter_open=False).mean() - sen.black_level_dn
             for t in (50.0, 200.0)]
    assert darks[1] / darks[0] == pytest.approx(4.0, rel=0.03)


def test_noise_is_shot_plus_read():
    sen = SensorModel(column_fpn_sigma=0.0, dark_current_e_per_ms=0.0)
    rad = np.full((200, 50, 204), 1.0, dtype=np.float32)
    z = sen.expose(rad, 10.0, exposure_seed=3).astype(np.float64)
    b = s_idx(650)
    lam = 1.0 * sen.qe_for(204)[b] * sen.radiance_to_e_per_ms * 10.0
    var_expected = (lam + sen.read_noise_e ** 2) * sen.gain_dn_per_e ** 2 + 1 / 12
    assert z[..., b].var() == pytest.approx(var_expected, rel=0.08)


def test_saturation_clips_at_4095():
    sen = SensorModel()
    rad = np.full((4, 8, 204), 1e4, dtype=np.float32)
    z = sen.expose(rad, 10.0)
    assert z.max() == 4095 and (z[..., VIS] == 4095).all()


def test_nonlinear_response_and_true_inverse():
    for resp in ("gamma", "s-curve"):
        sen = SensorModel(response=resp)
        x = np.linspace(0, 4095, 1000)
        z = sen.response_dn(x)
        assert np.all(np.diff(z) > 0) and z[0] == pytest.approx(0) and z[-1] == pytest.approx(4095)
        assert not np.allclose(z, x, atol=5)
        np.testing.assert_allclose(sen.inverse_response_dn(z), x, atol=1e-3)
        np.testing.assert_allclose(sen.true_log_inverse_response(z[1:]), np.log(x[1:]), atol=1e-4)
    with pytest.raises(InputError):
        SensorModel(response="cubic")


def test_default_qe_silicon_like():
    qe = SensorModel().qe_for(204)
    wl = SPECIM_IQ_WAVELENGTHS
    peak = wl[np.argmax(qe)]
    assert 600 <= peak <= 700
    assert qe[0] < 0.4 * qe.max() and qe[-1] < 0.2 * qe.max()


def test_bracket_and_scene_folder(tmp_path):
    s = make_scene(lines=16, samples=12)
    sim = simulate_bracket(s, SensorModel(), [0.5, 2.0, 8.0], dark_lines=8)
    assert [e.shape for e in sim.exposures] == [(16, 12, 204)] * 3
    assert all(e.dtype == np.uint16 for e in sim.exposures)
    # darks differ per integration time (dark current ∝ t)
    assert sim.darks[2].mean() > sim.darks[0].mean() + 0.5
    np.testing.assert_array_equal(sim.truth, s.radiance)
    again = simulate_bracket(s, SensorModel(), [0.5, 2.0, 8.0], dark_lines=8)
    for a, b in zip(sim.exposures, again.exposures):
        np.testing.assert_array_equal(a, b)
    out = write_simulated_scene(sim, tmp_path / "sc")
    doc = json.loads((out / "scene.json").read_text())
    assert doc["format"] == "mehs-scene/1" and doc["truth"] == "truth/radiance.hdr"
    assert [e["status"] for e in doc["exposures"]] == ["complete"] * 3
    import spectral.io.envi as envi

    rec = doc["exposures"][1]
    hdr = out / rec["folder"] / "capture" / (rec["folder"].split("/")[-1] + ".hdr")
    img = envi.open(str(hdr))
    np.testing.assert_array_equal(np.asarray(img.open_memmap()), sim.exposures[1])
    with pytest.raises(InputError):
        write_simulated_scene(sim, tmp_path / "sc")  # never overwrite a raw capture
    with pytest.raises(InputError):
        simulate_bracket(s, SensorModel(), [2.0, 1.0])


def test_exact_poisson_when_read_noise_is_small():
    lam = 3.0
    sen = SensorModel(read_noise_e=0.0, column_fpn_sigma=0.0, black_level_dn=0.0,
                      dark_current_e_per_ms=0.0, gain_dn_per_e=1.0, qe=np.ones(204),
                      radiance_to_e_per_ms=1.0)
    z = sen.expose(np.full((100, 100, 204), lam, dtype=np.float32), 1.0).astype(np.float64)
    assert z.mean() == pytest.approx(lam, rel=0.01)
    assert z.var() == pytest.approx(lam, rel=0.02)
    # P(0) of a Poisson law (a rounded normal would give ~0.075)
    assert np.mean(z == 0) == pytest.approx(np.exp(-lam), abs=0.003)


def test_moving_scene_folder_has_moved_mask(tmp_path):
    import cv2

    s = make_scene(lines=16, samples=16, motion=True)
    sim = simulate_bracket(s, SensorModel(), [1.0, 4.0, 16.0], dark_lines=2)
    out = write_simulated_scene(sim, tmp_path / "m")
    doc = json.loads((out / "scene.json").read_text())
    mask = cv2.imread(str(out / doc["truth_moved_mask"]), cv2.IMREAD_UNCHANGED)
    np.testing.assert_array_equal(mask > 0, s.moved_mask(3))
    assert doc["moved_mask_pixels"] == int(s.moved_mask(3).sum()) > 0


def test_bracket_seed_changes_noise_only():
    s = make_scene(lines=6, samples=6)
    a = simulate_bracket(s, SensorModel(), [1.0], dark_lines=2, white=False)
    b = simulate_bracket(s, SensorModel(), [1.0], dark_lines=2, white=False, seed=256)
    c = simulate_bracket(s, SensorModel(), [1.0], dark_lines=2, white=False, seed=256)
    assert not np.array_equal(a.exposures[0], b.exposures[0])
    np.testing.assert_array_equal(b.exposures[0], c.exposures[0])
    assert abs(a.exposures[0].astype(float).mean() - b.exposures[0].astype(float).mean()) < 1.0
