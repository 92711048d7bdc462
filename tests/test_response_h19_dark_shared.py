"""Shared response curves of dark brackets: which dark-offset solve ``offset="auto"`` keeps.

The rounds (log domain) never pin the free constant of ``f``: on a sodium-lamp scene at
10⁻³ of its light with a linear sensor, ``f(z_d)/f(300)`` ran 0.10 → 0.73 → 0.88 after 1,
60 and 300 rounds (the truth 0.11), and the merged radiance of its signal pixels was up to
14 % (3 exposures) or 29 % (2) off the true curve's in one brightness decile. The direct
solve (linear domain) gets 1–2 % there but 20–55 % on dark *gamma* brackets, where the
rounds' log-domain prior is the right one. ``auto`` now keeps the curve that fits held-out
pixels better (:mod:`mehs.synthesis.response_select`). Measured against the simulator's
true inverse response (``tests/_checks.signal_decile_excess``).
"""

import numpy as np
import pytest

from mehs.capture.scene import SPECIM_IQ_WAVELENGTHS, make_scene
from mehs.capture.sensor import SensorModel
from mehs.capture.simulate import simulate_bracket
from mehs.synthesis.fuse_response import recover_response
from _checks import bracket_of, signal_decile_excess


def _bracket(kind, scale, response, times, size=48):
    wl = SPECIM_IQ_WAVELENGTHS[::24]
    if kind == "natural":
        from mehs.scenes.natural import make_natural_scene

        scene = make_natural_scene(size, size, wl, seed=1)
    else:
        scene = make_scene(kind, lines=size, samples=size, wavelengths=wl, seed=1)
    scene.radiance = (scene.radiance * np.float32(scale)).astype(np.float32)
    sensor = SensorModel(response=response, seed=3)
    sim = simulate_bracket(scene, sensor, list(times))
    return sim, bracket_of(sim, wl), sensor


@pytest.mark.parametrize("kind, scale, response, times, limit", [
    # worst decile before (60 rounds) → now; the direct solve alone in brackets
    ("lamp", 1e-3, "linear", (1.0, 4.0, 16.0), 0.04),              # 14.2 % → 1.7 %
    ("lamp", 1e-3, "linear", (1.0, 16.0), 0.04),                   # 28.8 % → 1.0 %
    ("natural", 1e-3, "s-curve", (0.25, 1.0, 4.0, 16.0, 64.0), 0.07),  # 23.6 % → 4.6 %
    # gamma: the rounds are kept (direct 54.9 % and 20.2 %)
    ("lamp", 1e-2, "gamma", (1.0, 16.0), 0.04),                    # 2.0 %
    ("natural", 1e-3, "gamma", (0.25, 1.0, 4.0, 16.0, 64.0), 0.04),   # 1.2 %
])
def test_shared_curve_of_a_dark_bracket_follows_the_true_curve(kind, scale, response, times,
                                                               limit):
    sim, br, sensor = _bracket(kind, scale, response, times)
    curve = recover_response(br, shared=True)
    ex = signal_decile_excess(sim, br, sensor, curve)
    assert np.abs(ex).max() < limit, np.round(ex, 3)
    assert {"direct", "rounds"} <= set(curve.parameters["offset_misfit"])


def test_explicit_solves_are_still_what_was_asked_for():
    sim, br, sensor = _bracket("lamp", 1e-3, "linear", (1.0, 4.0, 16.0))
    for offset in ("rounds", "direct"):
        curve = recover_response(br, shared=True, offset=offset)
        assert curve.parameters["offset"] == offset
        assert "offset_misfit" not in curve.parameters


def test_per_band_curves_take_the_kept_shared_curve_as_reference():
    # the per-band reference was always the direct shared curve: on this dark gamma
    # bracket the bands' worst decile ran 22 % off the true curve's merge; now 1.2 %
    sim, br, sensor = _bracket("natural", 1e-3, "gamma", (0.25, 1.0, 4.0, 16.0, 64.0))
    curve = recover_response(br, shared=False)
    ex = signal_decile_excess(sim, br, sensor, curve)
    assert np.abs(ex).max() < 0.05, np.round(ex, 3)


def test_auto_without_held_out_pixels_keeps_the_rounds_and_saves(tmp_path):
    # 16² pixels: the shared solve samples every one, none is left to judge by
    from mehs.synthesis.response import ResponseCurve

    _, br, _ = _bracket("colorchecker", 1e-3, "gamma", (1.0, 4.0, 16.0), size=16)
    curve = recover_response(br, shared=True)
    assert curve.parameters["offset"] == "rounds"
    assert curve.parameters["offset_misfit"] == {"direct": None, "rounds": None}
    assert curve.parameters["offset_signal_p90"] < 4096 / 16
    back = ResponseCurve.load(curve.save(tmp_path / "r.json"))
    assert np.array_equal(back.g, curve.g) and back.parameters["offset_misfit"]["direct"] is None
