"""A response curve must rise with the level: a ``response.json`` whose ``g`` falls (hand
edited, another tool's) mapped two raw levels to one linear value and was fused without a
word. It is refused, naming the file and the level; mehs's own recovered curves rise and
load back."""

import json
import warnings

import numpy as np
import pytest

from mehs.capture.scene import make_scene
from mehs.capture.sensor import SensorModel
from mehs.capture.simulate import simulate_bracket
from mehs.cube import SpectralCube
from mehs.errors import FormatError
from mehs.synthesis.bracket import Bracket
from mehs.synthesis.fuse import fuse_bracket
from mehs.synthesis.response import ResponseCurve


def _bracket(n=32):
    wl = np.linspace(450.0, 900.0, 12)
    scene = make_scene("colorchecker", lines=n, samples=n, seed=2, wavelengths=wl,
                       fwhm=np.full(12, 20.0))
    sim = simulate_bracket(scene, SensorModel(seed=2, response="gamma"), [0.5, 2.0, 8.0],
                           seed=2, white=False)
    return Bracket([SpectralCube(e, wl) for e in sim.exposures], list(sim.darks), [None] * 3,
                   sim.times_ms, wl, bit_depth=12)


def _falling_file(tmp_path, level=1000, bands=None):
    g = np.log(np.maximum(np.arange(4096, dtype=np.float64), 0.5))
    if bands:
        g = np.repeat(g[None], bands, axis=0)
        g[1, level + 1] = g[1, level] - 0.2
    else:
        g[level + 1] = g[level] - 0.2
    path = ResponseCurve(g, 12, wavelengths=np.linspace(450.0, 900.0, bands) if bands else None
                         ).save(tmp_path / "response.json")
    return path


def test_falling_curve_is_refused_naming_file_and_level(tmp_path):
    path = _falling_file(tmp_path)
    with pytest.raises(FormatError) as err:
        ResponseCurve.load(path)
    msg = str(err.value)
    assert str(path) in msg and "level 1000 to 1001" in msg and "monotonic" in msg
    with pytest.raises(FormatError, match="level 1000"):
        fuse_bracket(_bracket(), response=path, ghosts="off")


def test_falling_band_is_named(tmp_path):
    path = _falling_file(tmp_path, level=77, bands=12)
    with pytest.raises(FormatError, match=r"band 1 \(.*nm\) falls from level 77"):
        ResponseCurve.load(path)


def test_recovered_curves_rise_and_load_back(tmp_path):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        for shared in (True, False):
            # a per-band 12-bit curve needs 4096 pixels
            res = fuse_bracket(_bracket(32 if shared else 66), response="debevec", ghosts="off",
                               check_response=False, shared_response=shared)
            path = res.response.save(tmp_path / f"r{shared}.json")
            assert np.array_equal(ResponseCurve.load(path).g, res.response.g)
    d = json.loads(path.read_text())
    assert d["format"] == "mehs-response/1"
