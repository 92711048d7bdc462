"""Luminance restoration of a network's fresh output in place (issue 16): pixels that
get the flat-spectrum fallback are filled where they are, not through a new image-sized
array."""

import tracemalloc

import numpy as np

from mehs.ssr.luminance import restore_luminance


def _case(seed=0, h=200, w=150, b=31):
    rng = np.random.default_rng(seed)
    S = rng.random((h, w, b), dtype=np.float32)
    S[::3] *= -1.0                    # a third of the spectra with no X+Y+Z: the fallback
    rgb = rng.random((h, w, 3), dtype=np.float32) * 4
    return S, rgb, np.arange(400, 710, 10, dtype=float)


def test_the_fallback_is_written_in_place():
    S, rgb, wl = _case()
    want = restore_luminance(S.copy(), rgb, wl)
    tracemalloc.start()
    try:
        got = restore_luminance(S, rgb, wl, overwrite=True)
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert got is S
    np.testing.assert_array_equal(got, want)
    # (per-pixel factors and masks only: far under the spectra's own bytes)
    assert peak < 0.5 * S.nbytes, peak


def test_without_overwrite_the_input_is_left_alone():
    S, rgb, wl = _case(1)
    keep = S.copy()
    out, n = restore_luminance(S, rgb, wl, return_fallback=True)
    np.testing.assert_array_equal(S, keep)
    assert n > 0 and out is not S
    flat = out[0, 0]
    np.testing.assert_allclose(flat, flat[0])          # a flat spectrum
