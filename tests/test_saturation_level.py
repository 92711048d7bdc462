"""A sensor that clips below the ADC's largest code: its plateau is found, not merged as signal.

The truth is the simulator's: :class:`~mehs.capture.sensor.SensorModel` clips the
electrons at ``full_well_e`` before the ADC, so a 14 000 e⁻ well at 0.25 DN/e⁻ and a
32 DN black level writes clipped samples at 3532 DN (± the column offsets and the
read noise, added after the clip: σ ≈ √(2² + 1.5²) DN), far
below 0.98·4095; the scene's radiance is known per band.
"""

from __future__ import annotations

import json

import numpy as np
import pytest

from mehs.capture.scene import SPECIM_IQ_WAVELENGTHS, make_scene
from mehs.capture.sensor import SensorModel
from mehs.capture.simulate import simulate_bracket
from mehs.cube import SpectralCube
from mehs.synthesis.bracket import Bracket
from mehs.synthesis.fuse import fuse_bracket
from mehs.synthesis.saturation import detect_saturation

DEFAULT = 0.98 * 4095
WL = SPECIM_IQ_WAVELENGTHS[::8]          # 26 bands


def _bracket(kind="colorchecker", full_well=20000.0, times=(8.0, 32.0, 128.0), ratio=300.0,
             size=48, post_clip_noise=0.0):
    sc = make_scene(kind, lines=size, samples=size, wavelengths=WL, source_ratio=ratio, seed=1)
    sen = SensorModel(seed=2, radiance_to_e_per_ms=1600.0, full_well_e=full_well)
    sim = simulate_bracket(sc, sen, list(times), seed=3, white=False)
    raws = sim.exposures
    if post_clip_noise:
        # more noise after the clip (on top of the simulator's read noise): the plateau spreads
        rng = np.random.default_rng(0)
        raws = [np.clip(np.rint(e + rng.normal(0, post_clip_noise, e.shape)), 0, 4095)
                .astype(np.uint16) for e in raws]
    br = Bracket([SpectralCube(e, sc.wavelengths) for e in raws], list(sim.darks),
                 [None] * len(times), sim.times_ms, sc.wavelengths, bit_depth=12)
    return sim, br


def _times_for_top(kind, ratio, top_dn):
    """Exposure times whose longest brings the brightest sample to ``top_dn`` (no clip)."""
    sc = make_scene(kind, lines=48, samples=48, wavelengths=WL, source_ratio=ratio, seed=1)
    peak = float((sc.radiance * SensorModel(radiance_to_e_per_ms=1600.0)
                  .signal_scale(WL.size, WL)).max())
    t = (top_dn - 32.0) / peak
    return (t / 16, t / 4, t)


def test_full_well_below_the_adc_is_found_and_the_radiance_is_not_read_low(capsys):
    sim, br = _bracket(full_well=14000.0)
    plateau = 14000 * 0.25 + 32
    assert sim.exposures[-1].max() < DEFAULT        # nothing reaches the default threshold
    res = fuse_bracket(br)
    assert res.response.is_linear
    # without the detection the clipped samples disagree with the shorter exposures:
    # 64 % of the pixels were flagged as ghosts
    assert res.summary["ghost_fraction"] < 0.01
    found = res.summary["saturation_detected"]
    assert found["detected"] and found["shared"]
    assert len(found["bands"]) + len(found["bands_extended"]) == WL.size
    assert np.all(np.abs(np.array(found["level_dn"]) - plateau) <= 2)
    sat = np.broadcast_to(np.asarray(found["saturation_dn"]), (WL.size,))
    # below every clipped sample (every column's offset), and only just: 5σ of the
    # plateau (σ = √(2² + 1.5² + 1/12) ≈ 2.5 DN: read noise after the clip, offsets)
    clipped = sim.exposures[-1] >= plateau - 6
    assert np.all(sim.exposures[-1][clipped] >= np.broadcast_to(sat, clipped.shape)[clipped])
    assert np.all(sat > plateau - 20)
    assert "clips below the ADC's largest code" in capsys.readouterr().err
    json.dumps(res.summary)                          # summary.json stays writable
    # the truth: samples clipped in the longest exposure (unclipped in the shortest)
    truth = sim.truth * sim.truth_dn_per_ms
    sel = (sim.exposures[-1] >= plateau - 6) & (sim.exposures[0] < plateau - 100)
    assert sel.sum() > 1000
    ratio = res.radiance.data[sel] / truth[sel]
    # without the detection: median 0.57, 1st percentile 0.17
    assert abs(np.median(ratio) - 1) < 0.01 and np.percentile(ratio, 1) > 0.9


def test_the_caller_saturation_wins(capsys):
    sim, br = _bracket(full_well=14000.0)
    res = fuse_bracket(br, response="linear", ghosts="off", saturation=DEFAULT)
    assert res.summary["saturation_detected"] is None
    assert "clips below" not in capsys.readouterr().err


def test_plateau_spread_by_read_noise_after_the_clip_is_found():
    sim, br = _bracket(full_well=14000.0, post_clip_noise=4.0)
    sat, found = detect_saturation(br)
    assert found["detected"] and found["shared"]
    # a few σ (√(4² + 1.5²) ≈ 4.3 DN) below the plateau in every band
    assert np.all((sat < 3532 - 3 * 4.3) & (sat > 3532 - 40)), sat
    clipped = sim.exposures[-1] >= 3532 - 6          # the truth: clipped before the noise
    noisy = np.asarray(br.exposures[-1].data)
    assert np.all(noisy[clipped] >= np.broadcast_to(sat, noisy.shape)[clipped])


@pytest.mark.parametrize("kind, ratio", [("colorchecker", 300.0), ("window", 300.0),
                                         ("colorchecker", 0.0), ("ramp", 0.0), ("lamp", 300.0)])
def test_no_clip_below_the_adc_no_detection(kind, ratio):
    # brightest sample ~3900 DN, nothing clipped: a lamp's uniform core, a smooth
    # glow, a window; "lamp" (sodium) piles its dim core up at ~75 DN between its lines
    sim, br = _bracket(kind, ratio=ratio, times=_times_for_top(kind, ratio, 3900.0))
    assert 3700 < sim.exposures[-1].max() < 4095
    sat, found = detect_saturation(br)
    assert not found["detected"], found
    np.testing.assert_array_equal(sat, np.float32(DEFAULT))


def test_adc_clip_at_its_largest_code_keeps_the_default():
    sim, br = _bracket()                 # 20 000 e⁻: the ADC clips at 4095 first
    assert (sim.exposures[-1] == 4095).mean() > 0.05
    sat, found = detect_saturation(br)
    assert not found["detected"]
    np.testing.assert_array_equal(sat, np.float32(DEFAULT))


def test_a_stuck_column_is_not_a_clip():
    sim, br = _bracket(times=_times_for_top("colorchecker", 0.0, 3000.0), ratio=0.0)
    raw = [np.array(e.data) for e in br.exposures]
    for e in raw:
        e[:, 7, 3] = 3300              # one column of one band stuck, in every exposure
    br2 = Bracket([SpectralCube(e, WL) for e in raw], br.darks, [None] * 3, br.times_ms, WL)
    sat, found = detect_saturation(br2)
    assert not found["detected"]


def test_cli_saturation_option(tmp_path, capsys):
    from mehs.capture.simulate import write_simulated_scene
    from mehs.cli import main

    sim, _ = _bracket(full_well=14000.0, size=24)
    scene = write_simulated_scene(sim, tmp_path / "s")
    args = ["fuse", str(scene), "--response", "linear", "--ghosts", "off", "--verify", "none"]
    assert main(args + ["--out", str(tmp_path / "auto")]) == 0
    s = json.loads((tmp_path / "auto" / "summary.json").read_text())
    assert s["saturation_detected"]["detected"]
    assert "mehs: notice:" in capsys.readouterr().err
    assert main(args + ["--out", str(tmp_path / "given"), "--saturation", "4000"]) == 0
    s = json.loads((tmp_path / "given" / "summary.json").read_text())
    assert s["saturation_detected"] is None
    assert main(args + ["--out", str(tmp_path / "bad"), "--saturation", "high"]) == 2
    assert "--saturation" in capsys.readouterr().err
