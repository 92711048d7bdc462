"""Debevec's merge of a linear sensor takes ``g(y) = ln y`` at the fractional ``y = raw − dark``.

The dark reference is a float per (column, band) — a mean of dark frames, growing with the
integration time — so ``raw − dark`` is not an integer level. ``ln E = Σ w(y)(ln y − ln t)
/ Σ w(y)`` (docs/science.md, design §3.2) with the rounded level in place of ``y`` was off
by up to ½ DN per sample: raws 42 / 72 / 192 at 1 / 4 / 16 ms gave 10.0 DN/ms for every
dark from 32.0 to 32.49 and 9.859 from 32.51, where the Poisson merge gives 10.0 … 9.927.
Debevec's hat weight takes the same argument as ``g`` (``w(z)``, ``g(z)`` of one ``z``),
the fractional ``y``; a weighting table is looked up at the rounded level.
"""

from __future__ import annotations

import numpy as np
import pytest
from _checks import assert_same_merge_bits

from mehs.synthesis.merge import NoiseModel, merge_bracket

L = 4096
TOP = L - 1


def _hat(z):
    z = np.clip(z, 0, TOP)
    return np.minimum(z, TOP - z) / (TOP / 2)


def _debevec_reference(stack, times, darks, floor, weight=None):
    """``exp(Σ w(y)(ln y − ln t) / Σ w(y))`` in float64, ``w = 0`` at or below ``floor``;
    every sample counts (right where all are unsaturated and usable)."""
    ys = [r.astype(np.float64) - d[None].astype(np.float64) for r, d in zip(stack, darks)]
    weight = weight or _hat
    num = 0.0
    den = 0.0
    for y, t in zip(ys, times):
        w = np.where(y > floor, weight(y), 0.0)
        num = num + w * (np.log(np.maximum(y, 0.5)) - np.log(t))
        den = den + w
    return np.where(den > 0, np.exp(num / np.where(den > 0, den, 1.0)), np.nan)


@pytest.mark.parametrize("dark", [32.0, 32.3, 32.49, 32.51, 32.7])
def test_one_sample_follows_the_fractional_dark_as_the_formula_and_poisson_do(dark):
    t = [1.0, 4.0, 16.0]
    stack = [np.full((1, 1, 1), v, np.uint16) for v in (42, 72, 192)]
    darks = [np.full((1, 1), dark)] * 3
    deb = float(merge_bracket(stack, t, method="debevec", darks=darks).radiance[0, 0, 0])
    poi = float(merge_bracket(stack, t, method="poisson", darks=darks).radiance[0, 0, 0])
    ref = float(_debevec_reference(stack, t, [d.astype(np.float32) for d in darks], 2.0)[0, 0, 0])
    assert deb == pytest.approx(ref, rel=2e-6)
    # (the three samples disagree by their quantisation: the two estimators differ by
    # their weights only, ≤ 0.03 %, where the rounded level was 0.7 % off at 32.51)
    assert deb == pytest.approx(poi, rel=3e-4)
    # old code: 10.0 at 32.3 / 32.49 (ref 9.957 / 9.931), 9.859 at 32.51 / 32.7 (9.928 / 9.901)


def _consistent_bracket(seed=0, nl=5, ns=23, nb=7):
    """Integer raws whose dark-subtracted values are exactly ``E·t``: the dark (a float
    per column and band, growing with ``t``) takes the fraction."""
    rng = np.random.default_rng(seed)
    t = np.array([1.0, 4.0, 16.0])
    E = rng.uniform(0.6, 200, (nl, ns, nb))
    stack, darks = [], []
    for tj in t:
        raw = np.floor(E * tj + 30 + 0.4 * tj + 1.0)
        # a dark that makes raw − dark = E·t exactly for a pixel of line 0: the other
        # lines' raws are rounded from E·t + dark with that same dark
        d = (raw[0] - E[0] * tj).astype(np.float32)
        raw[1:] = np.rint(E[1:] * tj + d[None])
        stack.append(raw.astype(np.uint16))
        darks.append(d)
    return stack, t, darks, E


@pytest.mark.parametrize("consistency", [True, False])
def test_consistent_samples_give_their_radiance_like_poisson(consistency):
    """Line 0: ``y_j = E·t_j`` to float32 rounding, so Debevec, Poisson and the truth agree
    (the rounded level was up to ½/y off: 4 % at the 0.6 DN/ms pixels' 12 DN);
    the other lines (integer raws of fractional ``E·t + dark``): the formula in float64."""
    stack, t, darks, E = _consistent_bracket()
    assert np.abs(darks[0] - np.rint(darks[0])).max() > 0.3     # fractional darks
    kw = dict(darks=darks, consistency=consistency, noise=NoiseModel(1.0, 2.0))
    deb = np.asarray(merge_bracket(stack, t, method="debevec", **kw).radiance, np.float64)
    poi = np.asarray(merge_bracket(stack, t, method="poisson", **kw).radiance, np.float64)
    np.testing.assert_allclose(deb[0], E[0], rtol=1e-5)
    np.testing.assert_allclose(poi[0], E[0], rtol=1e-5)
    ref = _debevec_reference(stack, t, darks, 2.0)
    np.testing.assert_allclose(deb, ref, rtol=1e-5)


def test_a_weighting_table_keeps_its_level_and_takes_ln_of_the_fractional_y():
    """The stage kernel's table-weight path of a linear sensor: ``w`` looked up at the
    rounded level, ``g(y) = ln y`` at the fractional ``y``."""
    from mehs.synthesis.response import weight_hat

    stack, t, darks, E = _consistent_bracket(seed=1)
    table = weight_hat(L) * 0.75
    deb = np.asarray(merge_bracket(stack, t, method="debevec", darks=darks,
                                   noise=NoiseModel(1.0, 2.0),
                                   weighting=lambda z: weight_hat(z.size) * 0.75).radiance,
                     np.float64)
    ref = _debevec_reference(stack, t, darks, 2.0,
                             weight=lambda y: table[np.clip(np.rint(y), 0, TOP).astype(int)])
    np.testing.assert_allclose(deb, ref, rtol=1e-5)
    np.testing.assert_allclose(deb[0], E[0], rtol=1e-5)


@pytest.mark.parametrize("consistency,clip", [(True, True), (False, False)])
def test_the_one_pass_kernel_equals_the_stage_kernel_with_fractional_darks(consistency, clip,
                                                                            monkeypatch):
    """Both kernels take ``y`` the same way: the same bits, on fractional darks, low
    samples about the floor and below zero, saturated and censored samples."""
    from mehs.synthesis import _merge_fused_weighted
    from mehs.synthesis._merge_kernels import merge_chunk
    from mehs.synthesis._merge_rows import DEBEVEC
    from mehs.synthesis.response import ResponseCurve, weighting_table

    rng = np.random.default_rng(4)
    t = np.array([1.0, 3.0, 11.0, 40.0])
    E = np.exp(rng.uniform(np.log(0.02), np.log(3000), (6, 29, 1))) * rng.uniform(0.3, 1, (1, 1, 9))
    darks = [30 + 0.3 * tj + rng.uniform(-0.5, 0.5, (29, 9)) for tj in t]
    stack = []
    for j, tj in enumerate(t):
        x = E * tj + darks[j][None] + rng.normal(0, 2, E.shape)
        if j == len(t) - 1:
            x[:2, :4] += 5000
        stack.append(np.clip(np.rint(x), 0, TOP).astype(np.uint16))
    kw = dict(method="debevec", darks=darks, consistency=consistency, clip_negative=clip,
              noise=NoiseModel(0.8, 2.5, relative=0.01))
    fused = merge_bracket(stack, t, **kw)
    glut = ResponseCurve.linear(12).table().astype(np.float32)
    wlut = weighting_table("hat", L).astype(np.float32)
    seen = []

    def stage(zs, darks, sat, times, L_, floor, gain, avar, rel_var, cal, want_chi2, clip_,
              *outs):
        seen.append(1)
        merge_chunk(zs, darks, sat, times, True, False, glut, np.exp(glut), wlut, True, True,
                    floor, gain, avar, rel_var, cal, DEBEVEC, want_chi2, clip_, *outs)

    monkeypatch.setattr(_merge_fused_weighted, "merge_chunk_debevec_linear", stage)
    monkeypatch.setattr(_merge_fused_weighted, "merge_chunk_debevec_linear_radiance", stage)
    ref = merge_bracket(stack, t, **kw)
    assert seen
    assert_same_merge_bits(fused, ref)
    # and both follow the fractional y where every sample is usable
    free = (E * t[-1] < 2500) & (E * t[0] > 6)
    free[:2, :4] = False
    assert free.sum() > 200
    want = _debevec_reference(stack, t, [d.astype(np.float32) for d in darks], 2.5)
    np.testing.assert_allclose(np.asarray(fused.radiance)[free], want[free], rtol=1e-5)
