"""The photon-transfer line of :func:`mehs.synthesis._ptc_groups._noise_curve` on the
linearised data of a diverged response curve: variances that overflow float64 used to end
in a bare ``ZeroDivisionError`` (``np.average`` of weights that all underflowed to 0)."""

import numpy as np
import pytest

from mehs.errors import InputError
from mehs.synthesis._ptc_groups import _noise_curve


def _groups(scale, n=4096, groups=8):
    rng = np.random.default_rng(0)
    g = np.repeat(np.arange(groups), n // groups)
    q = (g + 1.0) * 100.0
    e = rng.normal(0.0, 1.0, n) * np.sqrt(q) * scale          # σ² = q·scale²
    sig = np.full(groups, np.sqrt(800.0) * 3 * scale)
    return e, q, g, groups, sig


def test_variances_overflowing_in_every_group_raise_a_clear_error():
    e, q, g, groups, sig = _groups(1e160)            # e ~ 1e162: e² → inf
    with pytest.raises(InputError, match="overflows in every signal group"):
        _noise_curve(e, q, g, groups, sig, 3)


def test_huge_but_finite_variances_still_give_a_line():
    # e² ~ 1e203: finite, but 1/e⁴ underflowed to 0 and the flat fit divided by zero
    e, q, g, groups, sig = _groups(1e100)
    a, c = _noise_curve(e, q, g, groups, sig, 3)
    assert np.isfinite(a) and np.isfinite(c) and c > 0


def test_ordinary_noise_is_unchanged_by_the_guard():
    e, q, g, groups, sig = _groups(1.0)
    a, c = _noise_curve(e, q, g, groups, sig, 3)
    assert a == pytest.approx(1.0, rel=0.15)         # σ² = q: the shot-noise line
