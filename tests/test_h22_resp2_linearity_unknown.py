"""A bracket whose linearity cannot be tested ("no well-exposed signal level seen by two
exposures") used to be merged with the linear curve, silently: a 3-band, 2-exposure
bracket of a gamma-0.8 sensor (window scene, light ×1/50) then gave 3–6 % false ghosts on
a static scene, and nothing told the user. The linear curve is still used (a curve recovered
from such starved data is not vouched for by its self-check: on a linear sensor's dark bracket
a "determined" one ran +8…−3 %), but the scene is flagged — with the response check on or off."""

import warnings

import numpy as np
import pytest

from mehs.capture.scene import make_scene
from mehs.capture.sensor import SensorModel
from mehs.capture.simulate import simulate_bracket
from mehs.cube import SpectralCube
from mehs.synthesis.bracket import Bracket
from mehs.synthesis.fuse import ResponseUndeterminedWarning, fuse_bracket


@pytest.mark.parametrize("check", [True, False])
def test_unknown_linearity_is_flagged_not_silent(check):
    wl = np.array([460.0, 540.0, 610.0])
    scene = make_scene("window", lines=48, samples=48, seed=1, wavelengths=wl,
                       fwhm=np.full(3, 60.0), source_ratio=50.0)
    sim = simulate_bracket(scene, SensorModel(seed=1, response="gamma"), [0.5, 2.0], seed=1,
                           white=False)
    br = Bracket([SpectralCube(e, wl) for e in sim.exposures], list(sim.darks), [None] * 2,
                 sim.times_ms, wl, bit_depth=12)
    with warnings.catch_warnings(record=True) as got:
        warnings.simplefilter("always")
        res = fuse_bracket(br, ghosts="off", check_response=check)
    info = res.summary["response"]
    assert "linearity unknown" in info["linearity_check"]
    assert res.summary["response_undetermined"]
    assert res.response.is_linear and "linearity unknown" in info["assumed_linear"]
    assert any(isinstance(w.message, ResponseUndeterminedWarning)
               and "linearity unknown" in str(w.message) for w in got)
