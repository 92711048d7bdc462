"""Compiled (numba) merge of a bracket, one chunk of lines at a time.

Two entry points, so that a run compiles only what it uses (a first-ever
``mehs fuse`` with the default Poisson merge compiles the small kernel only):

- :func:`merge_chunk_poisson` — the Poisson (Hanji 2020) estimator of a non-linear
  sensor (a linear one's, the default, is :mod:`mehs.synthesis._merge_fused`);
- :func:`merge_chunk` — Debevec, Robertson and inverse-variance weights.

Both share the per-row stages of :mod:`mehs.synthesis._merge_rows` (sample
selection, pooled estimate, consistency statistic, output), inlined at numba level
so that LLVM sees each row's scratch as distinct arrays and vectorises (as separate
functions the aliasing checks defeated it: 6× slower). The kernels are serial and release
the GIL; :func:`mehs.synthesis.merge.merge_bracket` runs chunks of lines on a
thread pool. numba's ``parallel=True`` compiled for 16 s (one signature, the
Poisson kernel) against 4.6 s without it — most of a first-ever run (issue 16).
The per-row scratch (a few kB) stays in L1. The one transcendental in a hot loop,
Debevec's ``exp``, is :func:`~mehs.synthesis._merge_rows._exp_row` (Cephes ``expf``,
vectorisable; a scalar ``expf`` per sample made Debevec slower than OpenCV's; issue 16).
"""

from __future__ import annotations

import numpy as np
from numba import njit

from mehs.synthesis._merge_rows import (DEBEVEC, INVVAR, ROBERTSON, _chi2_censored,
                                        _chi2_sums, _exp_row, _fallback_row,
                                        _log_accumulate_row, _pool_row, _select_row, _write_row)


@njit(nogil=True, cache=True, error_model="numpy")
def merge_chunk_poisson(zs, darks, sat, times, linear, dark_after, elut, L,
                        gain, avar, rel_var, cal, want_chi2, clip,
                        out, chi2, dof, snr, nsat, nvalid, msum):
    """Poisson merge ``X = Σy / Σt`` of one chunk of lines (BIL); see :func:`merge_chunk`."""
    P = len(zs)
    nl, nb, ns = out.shape
    shared = elut.shape[0] == 1
    f0 = np.float32(0.0)
    f1 = np.float32(1.0)
    g32 = np.float32(gain)
    rel32 = np.float32(rel_var)
    for l in range(nl):
        y = np.empty((P, ns), dtype=np.float32)
        ok = np.empty((P, ns), dtype=np.float32)
        om = np.empty((P, ns), dtype=np.float32)
        cs = np.empty((P, ns), dtype=np.float32)
        lev = np.zeros((P, ns), dtype=np.int32)
        scratch = np.empty((10, ns), dtype=np.float32)
        sy, st, st2, sav, nv, nc, X, den, ysat, nsa = (
            scratch[0], scratch[1], scratch[2], scratch[3], scratch[4], scratch[5],
            scratch[6], scratch[7], scratch[8], scratch[9])
        for i in range(ns):
            nsa[i] = f0
        had_bad = False
        for a in range(nb):
            cb = 0 if shared else a
            s = sat[a]
            any_cens = _select_row(zs, l, a, cb, darks, s, times, avar, linear, dark_after,
                                   elut, L, g32, y, ok, cs, lev, ysat, sy, st, st2, sav, nv, nc)
            # X = Σy/Σt and, in the same pass, Σω²var = gain·X·Σt + Σa + rel·X²·Σt² for
            # the weights ω = t (Σω = Σt): no per-sample pass for the SNR
            nbad = False
            for i in range(ns):
                has = nv[i] > f0
                sti = st[i]
                xi = sy[i] / (sti if has else f1)
                X[i] = xi
                x = xi if xi >= f0 else f0
                den[i] = g32 * x * sti + sav[i] + rel32 * x * x * st2[i]
                nbad = nbad | (not has)
            # (where no sample is usable the SNR is 0 whatever den holds)
            had_bad = _fallback_row(zs, l, a, s, times, y, nv, X, nsa, had_bad, nbad)
            if want_chi2:
                _chi2_sums(times, avar, g32, rel32, ok, y, om, X, sy, st2, sav)
                if any_cens:
                    _chi2_censored(times, om, cs, sy, st2, sav)
            _write_row(X, clip, cal[a], st, den, nv, nsa, P, want_chi2, any_cens, sy, st2, sav,
                       nc, out[l, a], snr[l], msum[l], nvalid[l], nsat[l], chi2[l], dof[l])


@njit(nogil=True, cache=True, error_model="numpy")
def merge_chunk(zs, darks, sat, times, linear, dark_after, glut, elut, wlut, hat, lin_g,
                floor, gain, avar, rel_var, cal, method, want_chi2, clip,
                out, chi2, dof, snr, nsat, nvalid, msum):
    """Merge one chunk of lines of a bracket (band-interleaved-by-line layout).

    Parameters
    ----------
    zs : tuple of P arrays (lines, bands, samples)
        Raw DN of each exposure (shortest first), all of one array type.
    darks : float32 (P, bands, samples)
        Dark level per exposure (already linearised when ``dark_after``).
    sat : float32 (bands,)
        Raw DN at or above which a sample counts as saturated.
    times : float32 (P,)
        Exposure times (ms), ascending.
    linear : bool
        ``True``: linear sensor, ``y = raw − dark``.
    dark_after : bool
        Non-linear: ``y = exp(g(raw)) − dark`` (dark linearised); otherwise
        ``y = exp(g(round(raw − dark)))``.
    glut, elut : float32 (C_lut, L)
        g and exp(g) per band (C_lut = 1 for a shared curve).
    wlut : float32 (L,)
        Level weights (Debevec / Robertson).
    hat : bool
        ``wlut`` is Debevec's hat ``min(z, L−1−z)/((L−1)/2)``: computed, not looked up
        (a table gather per sample does not vectorise: LLVM cannot rule out aliasing).
    lin_g : bool
        ``glut`` is the linear curve ``ln max(z, ½)``: computed with :func:`_log_accumulate_row`,
        for a linear sensor at the fractional ``y = raw − dark`` (not the rounded level).
    floor : float32
        Debevec only: samples with y ≤ floor get zero weight (``ln y`` needs y > 0).
    gain : float
        Shot-noise gain (DN per electron) of the linearised y.
    avar : float32 (P,)
        Variance of y at zero signal for each exposure (read noise, dark-current
        shot noise, quantisation, dark-reference error).
    rel_var : float
        Squared systematic relative error (response-curve error).
    cal : float32 (bands,)
        Radiometric calibration factor per band.
    method : int
        DEBEVEC, ROBERTSON or INVVAR (POISSON: :func:`merge_chunk_poisson`).
    want_chi2 : bool
        Accumulate the ghost statistic.
    clip : bool
        Write negative (noise) estimates as 0.

    Outputs (written in place): ``out`` float32 (lines, bands, samples);
    per pixel (lines, samples): ``chi2`` float32 consistency statistic,
    ``dof`` int32, ``snr`` float32 (summed over bands), ``nsat`` int32 bands
    saturated in every exposure, ``nvalid`` int32 bands with a usable sample,
    ``msum`` float32 sum over bands of the output.

    Sample selection: :func:`_select_row`; the consistency statistic
    (:func:`_chi2_sums`) is taken about the inverse-variance mean of the usable
    samples whatever the method, so ghost decisions do not depend on it.
    """
    P = len(zs)
    nl, nb, ns = out.shape
    L = wlut.shape[0]
    shared = glut.shape[0] == 1
    f0 = np.float32(0.0)
    f1 = np.float32(1.0)
    half = np.float32(0.5)
    top = np.float32(L - 1)
    hmid = np.float32((L - 1) / 2.0)
    g32 = np.float32(gain)
    rel32 = np.float32(rel_var)
    fl = np.float32(floor)
    for l in range(nl):
        y = np.empty((P, ns), dtype=np.float32)
        ok = np.empty((P, ns), dtype=np.float32)
        om = np.empty((P, ns), dtype=np.float32)
        cs = np.empty((P, ns), dtype=np.float32)
        lev = np.zeros((P, ns), dtype=np.int32)
        scratch = np.empty((18, ns), dtype=np.float32)
        sy, st, st2, sav, nv, nc, X, num, den, ysat, nsa, XP, q, ex, lv, gz, s1, s2 = (
            scratch[0], scratch[1], scratch[2], scratch[3], scratch[4], scratch[5],
            scratch[6], scratch[7], scratch[8], scratch[9], scratch[10], scratch[11],
            scratch[12], scratch[13], scratch[14], scratch[15], scratch[16], scratch[17])
        for i in range(ns):
            nsa[i] = f0
        had_bad = False
        for a in range(nb):
            cb = 0 if shared else a
            s = sat[a]
            any_cens = _select_row(zs, l, a, cb, darks, s, times, avar, linear, dark_after,
                                   elut, L, g32, y, ok, cs, lev, ysat, sy, st, st2, sav, nv, nc)
            nbad = _pool_row(sy, st, nv, X)
            had_bad = _fallback_row(zs, l, a, s, times, y, nv, X, nsa, had_bad, nbad)
            for i in range(ns):
                XP[i] = max(X[i], f0)
                num[i] = f0
                den[i] = f0
            for j in range(P):
                tj = times[j]
                aj = avar[j]
                lt = np.float32(np.log(tj))
                okj = ok[j]
                yj = y[j]
                omj = om[j]
                lj = lev[j]
                if method == INVVAR:
                    # variance predicted from the pooled estimate, not from y_j
                    # itself (which would give low samples more weight: biased)
                    for i in range(ns):
                        w = okj[i] * tj * tj / (g32 * XP[i] * tj + aj)
                        omj[i] = w
                        num[i] += w * yj[i] / tj
                        den[i] += w
                elif method == ROBERTSON:
                    if linear and hat:
                        # the level weight of the *expected* level X·t: the
                        # sample's own level would favour upward noise (bias)
                        for i in range(ns):
                            lvi = np.float32(np.int32(min(max(XP[i] * tj + half, f0), top)))
                            w = okj[i] * (min(lvi, top - lvi) / hmid) * tj * tj
                            omj[i] = w
                            num[i] += w * yj[i] / tj
                            den[i] += w
                        continue
                    if linear:
                        for i in range(ns):
                            lv[i] = np.float32(np.int32(min(max(XP[i] * tj + half, f0), top)))
                    else:
                        for i in range(ns):
                            lv[i] = np.float32(lj[i])
                    if hat:
                        for i in range(ns):
                            w = okj[i] * (min(lv[i], top - lv[i]) / hmid) * tj * tj
                            omj[i] = w
                            num[i] += w * yj[i] / tj
                            den[i] += w
                    else:
                        for i in range(ns):
                            w = okj[i] * wlut[np.int32(lv[i])] * tj * tj
                            omj[i] = w
                            num[i] += w * yj[i] / tj
                            den[i] += w
                else:
                    if linear and hat and lin_g and not dark_after:
                        # Debevec's own form at the fractional z = y = raw − dark (the
                        # dark is a float per column and band; the rounded level was off
                        # by up to ½ DN): g(z) = ln z and the hat weight of z, computed in
                        # one pass, then ln in _log_accumulate_row (max: y > floor ≥ ½
                        # wherever w > 0, it only keeps ln finite where w = 0)
                        for i in range(ns):
                            yv = yj[i]
                            lvi = min(max(yv, f0), top)
                            w = okj[i] * (min(lvi, top - lvi) / hmid)
                            omj[i] = w if yv > fl else f0
                            gz[i] = max(yv, half)
                        _log_accumulate_row(gz, omj, lt, num, den)
                        continue
                    if linear:
                        for i in range(ns):
                            lv[i] = np.float32(np.int32(min(max(yj[i] + half, f0), top)))
                    else:
                        for i in range(ns):
                            lv[i] = np.float32(lj[i])
                    # w(level), zero at or below the floor (ln y needs y > 0)
                    if hat:
                        for i in range(ns):
                            w = okj[i] * (min(lv[i], top - lv[i]) / hmid)
                            omj[i] = w if yj[i] > fl else f0
                    else:
                        for i in range(ns):
                            w = okj[i] * wlut[np.int32(lv[i])]
                            omj[i] = w if yj[i] > fl else f0
                    if dark_after:
                        # ln y of the linearised sample (positive wherever w > 0)
                        for i in range(ns):
                            gz[i] = yj[i] if omj[i] > f0 else f1
                        _log_accumulate_row(gz, omj, lt, num, den)
                    elif lin_g and linear:
                        # ln y of the fractional y (a table weight is of the rounded level)
                        for i in range(ns):
                            gz[i] = max(yj[i], half)
                        _log_accumulate_row(gz, omj, lt, num, den)
                    elif lin_g:
                        for i in range(ns):
                            gz[i] = max(lv[i], half)
                        _log_accumulate_row(gz, omj, lt, num, den)
                    else:
                        # g of the integer level, a table look-up
                        gl = glut[cb]
                        for i in range(ns):
                            w = omj[i]
                            num[i] += w * (gl[np.int32(lv[i])] - lt)
                            den[i] += w
            if method == DEBEVEC:
                for i in range(ns):
                    dn = den[i]
                    q[i] = num[i] / dn if dn > f0 else f0
                _exp_row(q, ex)
                for i in range(ns):
                    # both loaded first: a load on one arm only does not vectorise
                    xo = X[i]
                    xe = ex[i]
                    X[i] = xe if den[i] > f0 else xo
            else:
                for i in range(ns):
                    xo = X[i]
                    dn = den[i]
                    xw = num[i] / (dn if dn > f0 else f1)
                    X[i] = xw if dn > f0 else xo
            if method == DEBEVEC or method == ROBERTSON:
                for i in range(ns):
                    if den[i] == f0 and nv[i] > f0:
                        # usable samples, all with zero level weight: pooled estimate
                        for j in range(P):
                            om[j, i] = ok[j, i] * times[j]
            # noise-model SNR: Σω and Σω²·var with var from the (clipped) estimate
            for i in range(ns):
                num[i] = f0
                den[i] = f0
                s1[i] = f0
                s2[i] = f0
            for j in range(P):
                tj = times[j]
                aj = avar[j]
                okj = ok[j]
                omj = om[j]
                if method == DEBEVEC:
                    # as the one-pass Debevec kernel takes it: Σω²·var = g·x·Σω²/t +
                    # Σ(ω/t)²·a + rel·x²·Σω², the sums taken without x (same bits)
                    for i in range(ns):
                        w = omj[i]
                        r = w / tj
                        num[i] += okj[i] * w
                        s1[i] += okj[i] * w * r
                        s2[i] += okj[i] * r * r * aj
                        den[i] += okj[i] * w * w
                else:
                    for i in range(ns):
                        xi = X[i]
                        x = xi if (xi >= f0) & (xi < np.float32(np.inf)) else f0
                        v = (g32 * x * tj + aj) / (tj * tj) + rel32 * x * x
                        num[i] += okj[i] * omj[i]
                        den[i] += okj[i] * omj[i] * omj[i] * v
            if method == DEBEVEC:
                for i in range(ns):
                    xi = X[i]
                    x = xi if (xi >= f0) & (xi < np.float32(np.inf)) else f0
                    den[i] = g32 * x * s1[i] + s2[i] + rel32 * x * x * den[i]
            if want_chi2:
                # about the pooled estimate XP (not the method's), as for Poisson
                _chi2_sums(times, avar, g32, rel32, ok, y, om, XP, sy, st2, sav)
                if any_cens:
                    _chi2_censored(times, om, cs, sy, st2, sav)
            _write_row(X, clip, cal[a], num, den, nv, nsa, P, want_chi2, any_cens, sy, st2, sav,
                       nc, out[l, a], snr[l], msum[l], nvalid[l], nsat[l], chi2[l], dof[l])
