"""The photon-transfer probe is sized by samples (pixels × bands), not pixels alone.

A fixed 4096 pixels gave a bracket of 2–3 bands 8–12 thousand samples a pair (0.8 million
at 204 bands), and its gain scattered by −19 … +13 % around the simulator's sensor (gain
0.25 DN/e⁻, the truth here) over seeds of a 512² scene.
"""

from __future__ import annotations

import numpy as np
import pytest

from mehs.capture.scene import SPECIM_IQ_WAVELENGTHS, make_scene
from mehs.capture.sensor import SensorModel
from mehs.capture.simulate import simulate_bracket
from mehs.cube import SpectralCube
from mehs.synthesis import noise as N
from mehs.synthesis.bracket import Bracket
from mehs.synthesis.fuse import estimate_noise
from mehs.synthesis.response import ResponseCurve


def _blank(lines, samples, bands):
    wl = SPECIM_IQ_WAVELENGTHS[:bands]
    ex = [SpectralCube(np.zeros((lines, samples, bands), np.uint16), wl) for _ in range(2)]
    return Bracket(ex, [None, None], [None, None], np.array([1.0, 4.0]), wl, bit_depth=12)


@pytest.mark.parametrize("bands, pixels", [(204, 4096), (51, 4096), (48, 4096),
                                           (17, 11566), (3, 65536), (2, 65536)])
def test_the_probe_holds_its_samples_up_to_a_cap_on_pixels(bands, pixels):
    assert N.probe_pixels(N.PROBE_PIXELS, bands) == pixels
    probe = N.probe_bracket(_blank(512, 512, bands), np.full(bands, 4013, np.float32))
    # whole lines: the step through 512² pixels that reads at least ``pixels``, or all
    step = int(np.ceil(512 * 512 / pixels))
    assert probe.raw.shape[1] == len(range(step // 2, 512, step)) * 512
    # about PROBE_BANDS × PROBE_PIXELS samples (whole lines: a step rounded up), or the cap
    target = min(N.PROBE_PIXELS * max(N.PROBE_BANDS, bands),
                 N.PROBE_MAX_SCALE * N.PROBE_PIXELS * bands)
    assert 0.95 * target <= probe.raw.shape[1] * bands <= target


def test_a_short_scan_of_many_bands_probes_one_line():
    """4 lines × 9000 pixels of 48 bands: the step through the pixels is 9 lines, and the
    first probed line (step // 2 = 4) must still lie inside the scan."""
    probe = N.probe_bracket(_blank(4, 9000, 48), np.full(48, 4013, np.float32))
    assert probe.raw.shape[1] == 9000 and probe.lines.tolist() == [3]


def test_three_bands_measure_the_gain_as_many_do():
    # before (4096 pixels, 12288 samples a pair): −13.3, −4.7, −5.5, +1.4 %
    err = []
    for seed in range(1, 5):
        wl = SPECIM_IQ_WAVELENGTHS[[0, 102, 203]]
        sc = make_scene("window", lines=512, samples=512, wavelengths=wl, seed=seed)
        sen = SensorModel(seed=seed)
        sim = simulate_bracket(sc, sen, [0.5, 2.0, 8.0], seed=seed)
        b = Bracket([SpectralCube(e, wl) for e in sim.exposures], list(sim.darks),
                    [None] * 3, sim.times_ms, wl, bit_depth=12)
        model, info = estimate_noise(b, ResponseCurve.linear(12),
                                     np.full(3, 0.98 * 4095, np.float32))
        assert "fallback" not in info, info
        err.append(model.gain / sen.gain_dn_per_e - 1)
    assert max(abs(e) for e in err) < 0.04, err


@pytest.mark.parametrize("threads", ["1", "2", "3"])
@pytest.mark.parametrize("lines", [1, 5, 64])
def test_the_probe_holds_exactly_its_lines_of_every_exposure(threads, lines, monkeypatch,
                                                             tmp_path):
    # each exposure read in parts on threads (one part for one line): every probed line
    # of every exposure in its place, from an in-memory (L, S, B) cube and from a BIL
    # memmap (Specim's layout, transposed in memory)
    import sys

    if "numba" in sys.modules:
        import numba

        monkeypatch.setattr(numba, "get_num_threads", lambda: int(threads))
    monkeypatch.setenv("NUMBA_NUM_THREADS", threads)
    rng = np.random.default_rng(lines)
    ns, nb = 700, 17
    wl = SPECIM_IQ_WAVELENGTHS[:nb]
    cubes = [rng.integers(0, 4096, (lines, ns, nb)).astype(np.uint16) for _ in range(3)]
    bil = []
    for j, c in enumerate(cubes):
        path = tmp_path / f"e{j}.raw"
        np.ascontiguousarray(c.transpose(0, 2, 1)).tofile(path)
        bil.append(np.memmap(path, np.uint16, "r", shape=(lines, nb, ns)).transpose(0, 2, 1))
    darks = [np.full((ns, nb), 60.0 + j, np.float32) for j in range(3)]
    for data in (cubes, bil):
        b = Bracket([SpectralCube(d, wl) for d in data], darks, [None] * 3,
                    np.array([1.0, 4.0, 16.0]), wl, bit_depth=12)
        probe = N.probe_bracket(b, np.full(nb, 4013, np.float32), max_pixels=2 * ns)
        assert probe.lines.size >= 1 and probe.raw.dtype == np.float32
        for j in range(3):
            want = cubes[j][probe.lines].reshape(-1, nb).astype(np.float32)
            np.testing.assert_array_equal(probe.raw[j], want)
            np.testing.assert_array_equal(probe.dark[j], darks[j])
