"""A gamma sensor's recovered curve, checked where the black level matters: the radiance of
dark and bright pixels against the simulator's truth.

The black-level offset rounds of ``recover_response`` converge sublinearly; after the old
12 plain rounds the merged radiance ran from −10 % (darkest decile) to +2.6 % (brightest)
of the truth, while the self-check called the curve determined (1.8 %).
"""

import warnings

import numpy as np

from mehs.capture.scene import make_scene
from mehs.capture.sensor import SensorModel
from mehs.capture.simulate import simulate_bracket, write_simulated_scene
from mehs.synthesis.bracket import load_bracket
from mehs.synthesis.fuse import fuse_bracket


def _decile_bias(rad, truth, ok):
    lr = np.log(np.maximum(rad[ok], 1e-12) / truth[ok])
    tv = truth[ok]
    med = np.median(lr)           # one global scale: the curve's gauge
    qs = np.quantile(tv, np.linspace(0, 1, 11))
    return np.array([np.expm1(np.median(lr[(tv >= a) & (tv < b)]) - med)
                     for a, b in zip(qs[:-1], qs[1:])])


def test_gamma_sensor_radiance_has_no_brightness_dependent_bias(tmp_path):
    scene = make_scene("colorchecker", 32, 32, seed=1)
    sim = simulate_bracket(scene, SensorModel(seed=3, response="gamma"),
                           (0.04, 0.16, 0.64, 2.56, 10.24))
    folder = write_simulated_scene(sim, tmp_path / "s", overwrite=True)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        res = fuse_bracket(load_bracket(folder), response="debevec")
    rad = np.asarray(res.radiance.data, np.float64)
    truth = np.asarray(sim.truth, np.float64) * sim.truth_dn_per_ms
    ok = np.broadcast_to((res.mask == 0)[..., None] & (truth > 0), rad.shape)
    bias = _decile_bias(rad, truth, ok)
    assert np.ptp(bias) < 0.06 and np.abs(bias).max() < 0.04, np.round(bias, 3)


def test_check_flags_a_curve_whose_exposures_disagree(tmp_path):
    # 3 exposures ×8 of a gamma sensor: split halves and λ vs 10λ agree (1.9 %, both share
    # the curve's bias) while the radiance runs −8…+1 % of the truth; linearised by the
    # curve, consecutive exposures disagree by 4 %, which the check now reports
    scene = make_scene("colorchecker", 32, 32, seed=1)
    sim = simulate_bracket(scene, SensorModel(seed=3, response="gamma"), (0.1, 0.8, 6.4))
    folder = write_simulated_scene(sim, tmp_path / "s", overwrite=True)
    with warnings.catch_warnings(record=True) as got:
        warnings.simplefilter("always")
        # λ = 100 pinned: chosen from the data (None) this bracket takes λ = 1000, whose curve
        # is 0.24 % from the true curve's merge (λ = 100: 0.69 %; decile ptp 2.1 vs 3.0 %)
        # and passes the check (exposures 1.1 % apart)
        res = fuse_bracket(load_bracket(folder), response="debevec", smoothness=100.0)
    chk = res.summary["response"]["check"]
    assert chk["median"] < chk["threshold"]            # the old criterion alone passed it
    assert chk["exposure_consistency"] > 0.03 and not chk["determined"], chk
    assert res.summary["response_undetermined"]
    assert any("consecutive exposures" in str(w.message) for w in got)
