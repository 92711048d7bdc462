"""Guard: the fused cube is the same bytes for any numba thread count.

The merge runs chunks of lines and the response solver ranges of bands on numba's thread
count (:func:`mehs.synthesis._ranges.run_ranges`); no number may depend on how the work
was split. ``chunk_lines=4`` makes the 24-line scan several chunks, so two threads do split
it; the truth compared against is the single-threaded run.
"""

from __future__ import annotations

import numpy as np
import pytest


@pytest.mark.parametrize("response,method", [("linear", "poisson"),
                                             ("debevec", "robertson")])
def test_fusion_is_the_same_on_one_and_two_threads(response, method):
    numba = pytest.importorskip("numba")
    from mehs.capture.scene import make_scene
    from mehs.capture.sensor import SensorModel
    from mehs.capture.simulate import simulate_bracket
    from mehs.cube import SpectralCube
    from mehs.synthesis.bracket import Bracket
    from mehs.synthesis.fuse import fuse_bracket

    if numba.config.NUMBA_NUM_THREADS < 2:
        pytest.skip("numba runs on one thread here")
    sim = simulate_bracket(make_scene("colorchecker", 24, 24, motion=True, seed=7),
                           SensorModel(seed=3), (0.05, 0.4, 3.2), seed=0)
    wl = sim.wavelengths
    bracket = Bracket([SpectralCube(e, wl) for e in sim.exposures], sim.darks, [None] * 3,
                      sim.times_ms, wl, bit_depth=12)
    old = numba.get_num_threads()
    out = []
    try:
        for n in (1, 2):
            numba.set_num_threads(n)
            r = fuse_bracket(bracket, method=method, response=response, chunk_lines=4, seed=0)
            out.append((np.asarray(r.radiance.data).tobytes(), np.asarray(r.mask).tobytes(),
                        np.asarray(r.confidence).tobytes(), r.summary["ghost_fraction"]))
    finally:
        numba.set_num_threads(old)
    assert out[0] == out[1]
