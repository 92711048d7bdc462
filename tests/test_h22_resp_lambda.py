"""λ chosen from the data (``smoothness=None``): a stiffer λ only where held-out pixels do
not object, never worse than the default λ = 100 against the simulator's true curve; a λ
given explicitly is used as is."""

import warnings

import numpy as np

from mehs.capture.scene import SPECIM_IQ_WAVELENGTHS, make_scene
from mehs.capture.sensor import SensorModel
from mehs.capture.simulate import simulate_bracket
from mehs.cube import SpectralCube
from mehs.synthesis.bracket import Bracket
from mehs.synthesis.fuse import fuse_bracket
from mehs.synthesis.fuse_response import recover_response
from mehs.synthesis.response import ResponseCurve


def _bracket(sensor, times, scale=1.0, size=40):
    wl = SPECIM_IQ_WAVELENGTHS[::8]
    scene = make_scene("lamp", lines=size, samples=size, wavelengths=wl, seed=1)
    # a dark bracket: the longest exposure barely leaves the dark level
    scene.radiance = (scene.radiance * np.float32(scale)).astype(np.float32)
    sim = simulate_bracket(scene, sensor, list(times), seed=3)
    br = Bracket([SpectralCube(e, wl) for e in sim.exposures], list(sim.darks),
                 [None] * len(times), sim.times_ms, wl, bit_depth=12)
    return br, sim


def _ptp(br, sim, sensor, curve):
    """ptp of the brightness-decile medians of ``curve``'s merge over the true curve's."""
    z = np.arange(4096, dtype=np.float64)
    true = ResponseCurve(np.log(np.maximum(sensor.inverse_response_dn(z), 1e-3)), 12,
                         parameters={"levels": "raw"})
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        got, ref = (fuse_bracket(br, response=c, ghosts="off", check_response=False)
                    for c in (curve, true))
    rad, rr = (np.asarray(r.radiance.data, np.float64) for r in (got, ref))
    truth = np.asarray(sim.truth, np.float64) * sim.truth_dn_per_ms
    ok = (((got.mask == 0) & (ref.mask == 0))[..., None] & (rad > 0) & (rr > 0)
          & (truth * float(sim.times_ms.max()) >= 20.0))
    q = np.log(rad[ok] / rr[ok])
    tv = truth[ok]
    qs = np.quantile(tv, np.linspace(0, 1, 11))
    return float(np.ptp([np.median(q[(tv >= a) & (tv <= b)]) for a, b in zip(qs[:-1], qs[1:])]))


def test_s_curve_knee_and_dark_bracket_keep_the_default():
    # an s-curve's knee: λ = 300 raised the held-out misfit by 13 %, its radiance ptp 2.2 →
    # 5.3 % (48², 51 bands); a dark bracket (×10⁻³ light) is not offered a stiffer λ
    for resp, scale in (("s-curve", 1.0), ("gamma", 1e-3)):
        sensor = SensorModel(response=resp, seed=3)
        br, sim = _bracket(sensor, (1.0, 4.0, 16.0), scale)
        auto = recover_response(br, shared=True)
        assert auto.smoothness == 100.0, (resp, auto.parameters.get("smoothness_choice"))
        fixed = recover_response(br, shared=True, smoothness=100.0)
        assert _ptp(br, sim, sensor, auto) <= _ptp(br, sim, sensor, fixed) + 1e-3


def test_gamma_sensor_takes_a_stiffer_lambda_and_records_it():
    # gamma 0.8, 7 exposures ×4: λ = 300 0.5 % ptp against λ = 100's 1.2 % (48²)
    sensor = SensorModel(response="gamma", seed=3)
    br, sim = _bracket(sensor, tuple(0.05 * 4.0 ** k for k in range(7)))
    auto = recover_response(br, shared=True)
    ch = auto.parameters["smoothness_choice"]
    print(ch)
    assert auto.smoothness > 100.0 and ch["chosen"] == auto.smoothness
    assert set(ch["misfit_rise"]) == {"100", "300", "1000"}
    fixed = recover_response(br, shared=True, smoothness=100.0)
    a, f = _ptp(br, sim, sensor, auto), _ptp(br, sim, sensor, fixed)
    print(a, f)
    assert a < f, (a, f)


def test_explicit_lambda_is_used_as_given():
    sensor = SensorModel(response="gamma", seed=3)
    br, _ = _bracket(sensor, tuple(0.05 * 4.0 ** k for k in range(7)))
    for lam in (100.0, 1000.0):
        curve = recover_response(br, shared=True, smoothness=lam)
        assert curve.smoothness == lam and "smoothness_choice" not in curve.parameters
