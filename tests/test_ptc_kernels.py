"""The photon-transfer statistics' compiled kernels (issue 16) equal numpy's, bit for bit.

The noise model and the linearity test of every ``mehs fuse`` rest on per-group means
and variances of ``d = y_k − r·y_j``; :mod:`mehs.synthesis._ptc_kernels` gathers the
subset that sets the groups and clips, and computes them in one pass, where numpy took ~30. The reference is the whole-array numpy formulation
(``tests/_ptc_reference.py``), run on the same probe.
"""

from __future__ import annotations

import numpy as np
import pytest
from _ptc_reference import pair_groups

from mehs.synthesis import _ptc_groups as G
from mehs.synthesis import noise as N


def _probe(seed=0, n=3000, nb=31, times=(1.0, 4.0, 16.0), gamma=1.0, sat_frac=0.05):
    """A probe of a static scene: shot + read noise, some saturated samples, negative
    dark-subtracted values, integer levels."""
    rng = np.random.default_rng(seed)
    E = np.exp(rng.uniform(np.log(0.3), np.log(400), (n, 1))) * rng.uniform(0.4, 1, (1, nb))
    E[rng.random(n) < sat_frac] *= 50                       # bright pixels: saturate
    ns = 20                                                  # columns of the probed lines
    n -= n % ns
    E = E[:n]
    dark = 64.0 + rng.normal(0, 1, (ns, nb)).astype(np.float32)
    raw = []
    for t in times:
        mu = 4095 * (np.clip(E * t, 0, 4095) / 4095) ** gamma
        x = rng.poisson(mu / 2.0) * 2.0 + rng.normal(0, 3, mu.shape) + np.tile(dark, (n // ns, 1))
        raw.append(np.clip(np.rint(x), 0, 4095))
    raw = np.stack(raw).astype(np.float32)
    sat = np.full(nb, 0.98 * 4095, np.float32)
    return N.ProbeSamples(raw, np.stack([dark] * len(times)).astype(np.float32),
                          np.asarray(times, np.float64), sat)


def _linear(raw, dark, j):
    return raw - dark


def _curve64(raw, dark, j):
    # a recovered curve's lineariser returns float64
    return (np.maximum(raw.astype(np.float64) - dark, 0.0) / 4095.0) ** 1.1 * 4095.0


@pytest.fixture(params=["numba", "stored", "numpy"])
def path(request, tmp_path, monkeypatch):
    """numba's dispatchers, the stored entry point, or (while a child process compiles
    that entry on a first-ever run) numpy's pass of ``mehs.synthesis._ptc_numpy``."""
    from mehs.synthesis import _native

    # the reference clips every group at 5 MAD σ and keeps every pixel, as mehs did
    # before its clip followed the noise at each sample's own level (a group's brightest
    # inlier's; pixels with a sample beyond it dropped: tests/test_noise_clip.py); the
    # passes are compared at the reference's clip
    real_clip = G._group_clip

    def no_far(*a):
        madz, qmax, far = real_clip(*a)
        return madz, qmax, np.zeros_like(far)

    monkeypatch.setattr(G, "_clip_sigma", lambda sig, *a: sig)
    monkeypatch.setattr(G, "_group_clip", no_far)
    monkeypatch.setattr(_native, "_loaded", {})
    monkeypatch.setenv("MEHS_CACHE_DIR", "" if request.param != "stored" else str(tmp_path))
    if request.param == "numpy":
        from mehs.synthesis import _ptc_numpy

        monkeypatch.setattr(_native, "building", lambda *a, **k: True)
        real = _ptc_numpy.ptc_pass

        def counted(*a):
            NUMPY_SUMS.append(1)
            return real(*a)

        monkeypatch.setattr(_ptc_numpy, "ptc_pass", counted)
    NUMPY_SUMS.clear()
    return request.param


NUMPY_SUMS: list = []


def _assert_equal(got, ref):
    assert (got is None) == (ref is None)
    if ref is None:
        return
    assert set(got) == set(ref)
    for k in ref:
        np.testing.assert_array_equal(np.asarray(got[k]), np.asarray(ref[k]), err_msg=k)


@pytest.mark.parametrize("lin", [_linear, _curve64], ids=["linear-float32", "curve-float64"])
@pytest.mark.parametrize("groups", [48, 300])        # 300: more groups than a uint8 holds
def test_pair_statistics_equal_numpys(path, lin, groups):
    from mehs.synthesis import _native

    probe = _probe(seed=groups)
    for j, k in ((0, 1), (1, 2)):
        _assert_equal(N._pair_groups_compute(probe, lin, j, k, groups, "k"),
                      pair_groups(probe, lin, j, k, groups))
    dtype = np.float32 if lin is _linear else np.float64
    assert _native.is_stored("ptc_pass", dtype) == (path == "stored")
    assert bool(NUMPY_SUMS) == (path == "numpy")       # the path under test was taken


def test_few_samples_use_them_all(path):
    # few pixels, many groups: the "subset" is every sample
    probe = _probe(seed=5, n=400, nb=9)
    assert probe.raw[0].size < 64 * G.CLIP_SAMPLES
    _assert_equal(N._pair_groups_compute(probe, _linear, 0, 1, 64),
                  pair_groups(probe, _linear, 0, 1, 64))


def test_groups_short_in_the_subset_use_all_their_samples(path, monkeypatch):
    # a dark scene of integer levels: whole cells of tied values fill some groups and
    # leave their neighbours short of CLIP_SAMPLES / 2 in the even subset; those groups'
    # medians come from all their samples, a second call (a spy on the medians: the
    # subset is no longer gathered by cells_flags, whose spy saw every call as this one)
    sizes, ds = [], []
    real = G._group_median_mad

    def spy(v, g, groups, *order):
        sizes.append(v.size)
        if order:                          # the subset's d (the fallback's call: no order)
            ds.append(v)
        return real(v, g, groups, *order)

    real_moving = G._moving_pixels

    def moving_spy(*a):
        # the moving pixels' z-scores take d about the final medians, those of the short
        # groups from all their samples (a stale e_s changed which pixels were scored)
        med, e_s, g_s = a[9], a[14], a[15]
        np.testing.assert_array_equal(e_s, ds[-1] - np.take(med, g_s))
        return real_moving(*a)

    monkeypatch.setattr(G, "_group_median_mad", spy)
    monkeypatch.setattr(G, "_moving_pixels", moving_spy)
    # a dark of whole codes: the dark-subtracted samples (and so the instrument) are
    # integers; d = y_k − r·y_j is not (r = 3.7), so a group's median from its subset
    # samples differs from that of all of them, and the statistics tell the two apart
    p = _probe(seed=0, n=4000, nb=60, times=(0.02, 0.074, 0.3))
    probe = N.ProbeSamples(p.raw, np.rint(p.dark), p.times_ms, p.saturation)
    assert probe.raw[0].size > 4 * 48 * G.CLIP_SAMPLES          # a real subset (step > 1)
    for j, k in ((0, 1), (1, 2)):
        _assert_equal(N._pair_groups_compute(probe, _linear, j, k, 48),
                      pair_groups(probe, _linear, j, k, 48))
    assert len(sizes) > 2                            # the fallback ran (for a pair)


def test_groups_with_saturation_are_dropped_as_before(path):
    probe = _probe(seed=7, sat_frac=0.4)
    st = N._pair_groups_compute(probe, _linear, 1, 2, 48)
    assert (st["nt"] == 0).any()                      # some groups dropped whole
    _assert_equal(st, pair_groups(probe, _linear, 1, 2, 48))


def test_nothing_usable_gives_none(path):
    probe = _probe(seed=1, n=50, nb=5)
    probe.raw[:] = 4095                               # saturated everywhere
    assert N._pair_groups_compute(probe, _linear, 0, 1, 48) is None


def test_decisions_from_the_pairs_side_by_side_are_those_of_one_at_a_time(monkeypatch):
    """The pairs run on threads; the noise model and linearity verdict are unchanged."""
    probe = _probe(seed=3, times=(1.0, 3.0, 9.0, 27.0))
    lin_par = N.linearity_PTC(probe, _linear, key="k")
    model_par, _ = N.estimate_noise_PTC(probe, _linear, key="k")
    monkeypatch.setattr(N, "_consecutive_pairs", lambda *a, **k: None)
    probe.cache.clear()
    lin_seq = N.linearity_PTC(probe, _linear, key="k")
    model_seq, _ = N.estimate_noise_PTC(probe, _linear, key="k")
    assert lin_par["deviation"] == lin_seq["deviation"]
    assert lin_par["ratios"] == lin_seq["ratios"]
    assert (model_par.gain, model_par.read_noise) == (model_seq.gain, model_seq.read_noise)
    # and the fit finds the simulated sensor: gain 2 DN/e-, read noise 3 DN
    assert model_par.gain == pytest.approx(2.0, rel=0.05)
    assert model_par.read_noise == pytest.approx(3.0, rel=0.15)


def test_the_stored_entry_point_checks_its_arrays(tmp_path, monkeypatch):
    from mehs.synthesis import _native

    monkeypatch.setattr(_native, "_loaded", {})
    monkeypatch.setenv("MEHS_CACHE_DIR", str(tmp_path))
    kernel = G._kernel(np.dtype(np.float32))
    assert _native.is_stored("ptc_pass", np.float32)
    n, nb, ng = 10, 6, 4
    y = np.zeros((n, nb), np.float32)
    rows = (np.empty(nb, np.int32), np.empty(nb, np.int32), np.empty(nb, np.uint8),
            np.empty(nb, np.uint8))
    sat = np.full(nb, 4000, np.float32)
    nbr = (np.arange(nb) ^ 1).astype(np.int64)
    table = np.array([0, 1, 2, 3], np.uint16)
    group = (2.0, 1 << 17, table, np.zeros(ng), np.ones(ng))
    sums = tuple(np.zeros(ng) for _ in range(6))
    kernel(y, y, y, y, sat, nbr, 18, *rows, *group, *sums)
    assert sums[0].sum() == n * nb                  # every sample counted once
    with pytest.raises(TypeError, match="y_k"):
        kernel(y, y[:5], y, y, sat, nbr, 18, *rows, *group, *sums)
    with pytest.raises(TypeError, match="nbr"):
        kernel(y, y, y, y, sat, nbr + nb, 18, *rows, *group, *sums)
    with pytest.raises(TypeError, match="one value per group"):
        kernel(y, y, y, y, sat, nbr, 18, *rows, *group, *sums[:5], np.zeros(ng + 1))
    with pytest.raises(TypeError, match="unknown groups"):
        kernel(y, y, y, y, sat, nbr, 18, *rows, 2.0, 1 << 17, table + 4, *group[3:], *sums)
    with pytest.raises(TypeError, match="outside the cells"):
        kernel(y, y, y, y, sat, nbr, 18, *rows, 2.0, (1 << 18) - 2, *group[2:], *sums)
    with pytest.raises(TypeError, match="raw_j must be a C-contiguous float32"):
        kernel(y, y, y.astype(np.float64), y, sat, nbr, 18, *rows, *group, *sums)


def _subset_reference(y_j, y_k, raw_j, raw_k, sat, step, r):
    """The even subset written out sample by sample from its definition."""
    from _ptc_reference import cells_of

    n, nb = y_j.shape
    nbr = np.arange(nb) ^ 1
    nbr[nbr >= nb] = nb - 2
    out = ([], [], [], [])
    for at in range(0, n * nb, step):
        p, b = divmod(at, nb)
        c = nbr[b]
        if raw_k[p, b] >= sat[b] or raw_k[p, c] >= sat[c] or raw_j[p, b] >= sat[b]:
            continue
        inst = np.float32(y_j[p, c] + y_k[p, c])
        a, k = float(y_j[p, b]), float(y_k[p, b])
        for lst, v in zip(out, (int(cells_of(np.array([inst]))[0]), k - r * a, r * (k + a), p)):
            lst.append(v)
    return out


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
@pytest.mark.parametrize("nb, step", [(7, 1), (7, 5), (31, 11), (2, 3)])
def test_the_subset_kernel_gathers_the_unsaturated_samples_of_every_step(path, dtype, nb,
                                                                        step):
    """(issue 16) the subset the groups and clips come from, gathered by one compiled
    loop: each path equals the samples written out one by one — the instrument of an
    odd probe's last band the band before it, the saturation of either exposure and of the
    instrument's longer one, −0.0 as +0.0, negative values."""
    from mehs.synthesis import _native

    rng = np.random.default_rng(nb * 100 + step)
    n = 40
    y_j = rng.normal(50, 80, (n, nb)).astype(dtype)
    y_k = (3.5 * y_j + rng.normal(0, 20, (n, nb))).astype(dtype)
    y_j[0, :] = -0.0                   # the instrument −0.0 + −0.0: the cell of +0.0
    y_k[0, :] = -0.0
    y_k[1, :] = 0.0
    raw_j = np.clip(y_j + 64, 0, None).astype(np.float32)
    raw_k = np.clip(y_k + 64, 0, None).astype(np.float32)
    sat = rng.uniform(200, 400, nb).astype(np.float32)
    r = 3.5
    nbr = G._instrument(y_j).astype(np.int64)
    m = -(-(n * nb) // step)
    outs = (np.full(m, -7, np.int32), np.full(m, np.nan), np.full(m, np.nan),
            np.full(m, -7, np.int64), np.zeros(1, np.int64))
    G._kernel(np.dtype(dtype), "ptc_subset")(y_j, y_k, raw_j, raw_k, sat, nbr, G.CELL_BITS,
                                              step, r, *outs)
    assert _native.is_stored("ptc_subset", dtype) == (path == "stored")
    ref = _subset_reference(y_j, y_k, raw_j, raw_k, sat, step, r)
    k = int(outs[4][0])
    assert 0 < k == len(ref[0]) < m                      # some kept, some saturated
    for got, want, t in zip(outs[:4], ref, (np.int32, np.float64, np.float64, np.int64)):
        np.testing.assert_array_equal(got[:k], np.asarray(want, t))
    assert (outs[0][k:] == -7).all()                    # nothing written past the count


def test_the_stored_subset_entry_point_checks_its_arrays(tmp_path, monkeypatch):
    from mehs.synthesis import _native

    monkeypatch.setattr(_native, "_loaded", {})
    monkeypatch.setenv("MEHS_CACHE_DIR", str(tmp_path))
    kernel = G._kernel(np.dtype(np.float32), "ptc_subset")
    assert _native.is_stored("ptc_subset", np.float32)
    n, nb, step = 10, 6, 4
    y = np.zeros((n, nb), np.float32)
    sat = np.full(nb, 4000, np.float32)
    nbr = (np.arange(nb) ^ 1).astype(np.int64)
    m = -(-(n * nb) // step)

    def outs(size=m, count=1):
        return (np.empty(size, np.int32), np.empty(size), np.empty(size),
                np.empty(size, np.int64), np.zeros(count, np.int64))

    o = outs()
    kernel(y, y, y, y, sat, nbr, 18, step, 2.0, *o)
    assert o[4][0] == m and (o[3] == np.arange(0, n * nb, step) // nb).all()
    with pytest.raises(TypeError, match="raw_k"):
        kernel(y, y, y, y[:5], sat, nbr, 18, step, 2.0, *outs())
    with pytest.raises(TypeError, match="nbr"):
        kernel(y, y, y, y, sat, nbr - 1, 18, step, 2.0, *outs())
    with pytest.raises(TypeError, match="step"):
        kernel(y, y, y, y, sat, nbr, 18, 0, 2.0, *outs())
    for i in range(4):                                 # each output too short alone
        short = list(outs())
        short[i] = short[i][:m - 1]
        with pytest.raises(TypeError, match=f"hold {m} samples"):
            kernel(y, y, y, y, sat, nbr, 18, step, 2.0, *short)
    with pytest.raises(TypeError, match="nbr"):
        kernel(y, y, y, y, sat, nbr + 1, 18, step, 2.0, *outs())
    with pytest.raises(TypeError, match="sat"):
        kernel(y, y, y, y, sat[:-1], nbr, 18, step, 2.0, *outs())
    with pytest.raises(TypeError, match="cell_bits"):
        kernel(y, y, y, y, sat, nbr, 25, step, 2.0, *outs())
    with pytest.raises(TypeError, match="step"):
        kernel(y, y, y, y, sat, nbr, 18, n * nb + 1, 2.0, *outs())
    # ctypes would pass 2**64 + step as step itself, past the check
    with pytest.raises(TypeError, match="not an int64"):
        kernel(y, y, y, y, sat, nbr, 18, 2 ** 64 + step, 2.0, *outs())
    read_only = list(outs())
    read_only[1].flags.writeable = False
    with pytest.raises(TypeError, match="ds must be writeable"):
        kernel(y, y, y, y, sat, nbr, 18, step, 2.0, *read_only)
    y_ro = y.copy()
    y_ro.flags.writeable = False                        # inputs may be read-only
    kernel(y_ro, y_ro, y_ro, y_ro, sat, nbr, 18, step, 2.0, *outs())
    with pytest.raises(TypeError, match="the count one"):
        kernel(y, y, y, y, sat, nbr, 18, step, 2.0, *outs(count=2))
    with pytest.raises(TypeError, match="cells must be a C-contiguous int32"):
        kernel(y, y, y, y, sat, nbr, 18, step, 2.0, np.empty(m, np.int64), *outs()[1:])
