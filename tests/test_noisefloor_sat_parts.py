"""The band noise model where exposures saturate: the parts, against the merge itself.

Where the longest exposures saturate, the merge pools only the shorter ones; the
all-exposures model understated those elements' noise (×150–×500 in variance for the
usual brackets). The model's steps come from the saturation levels and the merge's own
choice; here its variance is checked against merges of simulated Poisson–Gaussian samples.
"""

import numpy as np
import pytest

from mehs.dataset import noisefloor
from mehs.dataset.noisefloor_sat import usable_limits
from mehs.errors import InputError

GAIN, READ = 0.25, 2.0
NOISE = {"gain_dn_per_e": GAIN, "read_noise_dn": READ, "dark_current_dn_per_ms": 0.0,
         "relative": 0.0}


def _merged_variance(times, levels_dn_per_ms, sat_dn, n=4000, seed=0):
    """Empirical variance of the Poisson merge of ``n`` samples of each level (a band each)."""
    from mehs.synthesis.merge import NoiseModel, merge_bracket

    rng = np.random.default_rng(seed)
    x = np.asarray(levels_dn_per_ms, dtype=np.float64)
    stack = []
    for t in times:
        e = rng.poisson(np.broadcast_to(x * t / GAIN, (1, n, x.size)))
        y = e * GAIN + rng.normal(0.0, READ, e.shape)
        stack.append(np.clip(np.rint(y), 0, 4095).astype(np.uint16))
    r = merge_bracket(stack, times, method="poisson", saturation=sat_dn,
                      noise=NoiseModel(GAIN, READ, 0.0, 0.0), clip_negative=False,
                      consistency=False)
    return np.asarray(r.radiance, np.float64)[0].var(axis=0)


def test_the_model_follows_the_merge_past_each_saturation():
    """Merged variance per level, against the model with steps and the one without."""
    times = (0.05, 1.0, 20.0)
    sat = 4000.0
    ys = np.full((3, 1), sat)
    lim = usable_limits(NOISE, times, ys)[:, 0]          # DN/ms where each is dropped
    assert lim[0] == pytest.approx(sat / 0.05)
    assert lim[2] < sat / 20.0 and lim[1] < sat / 1.0    # a margin below saturation
    # levels clear of the steps (±8 %): every exposure, the two shorter, the shortest
    x = np.concatenate([np.geomspace(5, 0.92 * lim[2], 4), np.geomspace(1.08 * lim[2], 0.92 * lim[1], 4),
                        np.geomspace(1.08 * lim[1], 0.9 * lim[0], 4)])
    emp = _merged_variance(times, x, sat)
    model = noisefloor.band_noise_model(NOISE, times, np.eye(x.size), 1.0,
                                        saturation=np.full((3, x.size), sat))
    s = noisefloor.sigma(x[None].astype(np.float32), model)[0].astype(np.float64)
    np.testing.assert_allclose(emp / s ** 2, 1.0, atol=0.12)
    old = dict(model)
    old.pop("exposures")
    s_old = noisefloor.sigma(x[None].astype(np.float32), old)[0].astype(np.float64)
    # without the steps: right where every exposure is used, ×20–×400 short above
    np.testing.assert_allclose(emp[:4] / s_old[:4] ** 2, 1.0, atol=0.12)
    assert np.all(emp[4:8] / s_old[4:8] ** 2 > 10) and np.all(emp[8:] / s_old[8:] ** 2 > 200)


def test_steps_hold_the_shorter_exposures_poisson_variance():
    times = (1.0, 8.0, 64.0)
    noise = dict(NOISE, dark_current_dn_per_ms=0.1, relative=0.01)
    model = noisefloor.band_noise_model(noise, times, np.eye(2), np.array([2.0, 0.5]),
                                        saturation=np.full((3, 2), 3000.0))
    lev = np.asarray(model["exposures"]["levels"])
    assert lev.shape == (2, 2) and np.all(np.diff(lev, axis=1) > 0)
    y = np.asarray([[lev[0, 1] * 1.01, lev[1, 1] * 1.01]], np.float32)  # only t = 1 ms used
    a1 = READ ** 2 + GAIN * 0.1 * 1.0
    f = np.array([2.0, 0.5])
    x = y[0] / f
    expect = f * f * (GAIN * x / 1.0 + a1 + (0.01 * x) ** 2)
    np.testing.assert_allclose(noisefloor.sigma(y, model)[0] ** 2, expect, rtol=1e-4)
    # the radiance scale moves the steps with the values
    sc = noisefloor.scaled(model, 4.0)
    np.testing.assert_allclose(noisefloor.sigma(y * 4, sc), noisefloor.sigma(y, model) * 4,
                               rtol=1e-5)


def test_a_model_without_steps_reads_as_before():
    model = noisefloor.band_noise_model(NOISE, (1.0, 10.0), np.eye(3))
    assert "exposures" not in model
    y = np.array([[0.0, 5.0, 5e3]], np.float32)
    np.testing.assert_allclose(noisefloor.sigma(y, model) ** 2,
                               (READ ** 2 * 2 / 121 + GAIN * y / 11), rtol=1e-5)


@pytest.mark.parametrize("bad", [{"levels": [[1.0]] * 3, "zero": [1.0], "shot": [1.0]},
                                 {"levels": [[2.0, 1.0]] * 3, "zero": [1, 1], "shot": [1, 1],
                                  "rel": [1, 1]},
                                 {"levels": [[1.0]] * 2, "zero": [1], "shot": [1], "rel": [1]},
                                 {"levels": [[float("nan")]] * 3, "zero": [1], "shot": [1],
                                  "rel": [1]}])
def test_a_damaged_step_record_is_refused(bad):
    model = dict(noisefloor.band_noise_model(NOISE, (1.0, 10.0), np.eye(3)), exposures=bad)
    with pytest.raises(InputError, match="exposures"):
        noisefloor.sigma(np.ones((1, 3), np.float32), model)


def test_saturation_levels_of_the_wrong_shape_are_named():
    from mehs.dataset.noisefloor_sat import saturation_levels

    with pytest.raises(InputError, match="fusion.json 'saturation_linear_dn'"):
        saturation_levels({"saturation_linear_dn": [[1.0, 2.0]]}, 2)
    assert saturation_levels({}, 2) is None
