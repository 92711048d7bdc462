"""The stages of the compiled merge, one row (one line, one band) at a time.

Used by :mod:`mehs.synthesis._merge_kernels` (the weighted methods, and the Poisson merge
of a non-linear sensor): sample selection, pooled estimate, fallback, consistency
statistic, output, each a loop over the row's contiguous samples with selects only, so
that LLVM vectorises it; ``exp`` / ``ln`` of a row through the Cephes forms of
:mod:`mehs.synthesis._cephes` (pip's llvmlite has no SVML, and a libm call per sample
kept the loops scalar). The stages are inlined at numba level into the kernels
(``inline="always"``), so that LLVM sees each row's scratch as distinct arrays (as
separate functions the aliasing checks defeated it: 6× slower). ``fastmath`` stays off: the merge must give the same numbers as
the reference formulas, and NaN/inf checks must not be optimised away.

The constants here are shared with :mod:`mehs.synthesis._merge_fused`.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from mehs.synthesis._cephes import expf, logf

# Merge method codes shared with mehs.synthesis.merge.
DEBEVEC, ROBERTSON, POISSON, INVVAR = 0, 1, 2, 3

#: A sample of exposure j ≥ 1 is used only when the prediction from the shorter
#: exposures lies this many sigmas (squared) below saturation: the choice then
#: does not depend on the sample's own noise, so no truncation bias.
ROOM_SIGMA2 = np.float32(9.0)
#: A saturated sample predicted this far (sigmas², squared) below saturation is
#: evidence of change (a censored residual in the consistency statistic).
CENSOR_SIGMA2 = np.float32(25.0)
#: the shorter exposures' prediction counts as "too noisy to decide" when its variance
#: exceeds this multiple of the sample's own variance at saturation (σ ratio 2)
PREDICTION_NOISIER2 = np.float32(4.0)

@njit(cache=True, inline="always", error_model="numpy")
def _exp_row(x, out):
    """``out = exp(x)`` in float32, elementwise, vectorisable (Cephes ``expf``, ≤ 2 ulp;
    :func:`mehs.synthesis._cephes.expf`, which calls into no libm)."""
    for i in range(x.shape[0]):
        out[i] = expf(x[i])
    return out


@njit(cache=True, inline="always", error_model="numpy")
def _log_accumulate_row(x, w, lt, num, den):
    """``num += w·(ln x − lt)``, ``den += w``, for positive, finite, normal ``x``.

    ``ln`` is Cephes ``logf`` (≤ 2 ulp; :func:`mehs.synthesis._cephes.logf`, its
    ``frexp`` through a bitcast), so the loop vectorises.
    """
    for i in range(x.shape[0]):
        wi = w[i]
        num[i] += wi * (logf(x[i]) - lt)
        den[i] += wi


@njit(cache=True, inline="always", error_model="numpy")
def _usable(raw, yv, ys, s, tj, tj2, aj, g32, sy, st, sav):
    """Whether exposure j ≥ 1 of one sample is used, and whether it is censored.

    ``raw`` its DN, ``yv`` its linearised value, ``ys`` the linearised saturation level,
    ``s`` the raw one; ``sy``, ``st``, ``sav`` the running Σy, Σt and Σ zero-signal
    variance of the shorter exposures' usable samples. Returns ``(o, c)``: ``o`` 1.0
    if used (else 0.0); ``c`` True when the sample saturated although the shorter
    exposures predict it ``5σ`` below saturation. Scalars in, a pair out: numba
    inlines it into each kernel's sample loop and LLVM still vectorises the loop (a
    helper that returned a sample's whole running state, nine values, did stop it).
    """
    f0 = np.float32(0.0)
    f1 = np.float32(1.0)
    syi = max(sy, f0)
    # (ysat − predicted y)·Σt and the prediction's variance·(Σt)²
    room = ys * st - syi * tj
    vp = g32 * syi * tj * st + aj * st * st + tj2 * (g32 * syi + sav)
    r2 = room * room
    pos = room > f0
    unsat = raw < s
    # a prediction from exposures ×50–×200 shorter is far noisier than the sample
    # itself: then its own 3σ margin below saturation decides (a bias confined to a 3σ
    # band under saturation, instead of dropping every long sample whose short
    # prediction happened to be high)
    vown = g32 * max(ys, f0) + aj
    marg = ys - yv
    own = ((vp > PREDICTION_NOISIER2 * vown * st * st) & (marg > f0)
           & (marg * marg > ROOM_SIGMA2 * vown))
    o = f1 if unsat & ((st == f0) | (pos & (r2 > ROOM_SIGMA2 * vp)) | own) else f0
    c = (raw >= s) & (st > f0) & pos & (r2 > CENSOR_SIGMA2 * vp)
    return o, c


@njit(cache=True, inline="always", error_model="numpy")
def _select_row(zs, l, a, cb, darks, s, times, avar, linear, dark_after, elut, L, g32,
                y, ok, cs, lev, ysat, sy, st, st2, sav, nv, nc):
    """Choose the usable samples of row ``l``, band ``a``; return True if any is censored.

    Writes per exposure ``y`` (linearised DN), ``ok`` (1 = used), ``cs``
    (censored: the saturation level, else 0) and, for non-linear sensors,
    ``lev``; per sample the running sums ``sy`` (Σy), ``st`` (Σt), ``st2``
    (Σt²), ``sav`` (Σ zero-signal variance), ``nv`` (count) and ``nc``
    (censored count).

    Every unsaturated sample is used by the linear estimators, and exposure
    j ≥ 1 where the running Poisson estimate of the shorter exposures predicts
    it ``3σ`` below saturation — or, where that prediction is more than twice
    as noisy as the sample (brackets ×50–×200 apart, dark bands), where the
    sample itself lies ``3σ`` below saturation: deciding by a much noisier
    prediction dropped the long sample exactly where the short one had noise
    up, +15 % at 400 nm.
    """
    P = len(zs)
    ns = sy.shape[0]
    f0 = np.float32(0.0)
    f1 = np.float32(1.0)
    if not linear:
        # (the linear path's first exposure writes the sums instead of adding)
        for i in range(ns):
            sy[i] = f0
            st[i] = f0
            st2[i] = f0
            sav[i] = f0
            nv[i] = f0
            nc[i] = f0
    any_cens = False
    for j in range(P):
        zr = zs[j][l, a]
        dr = darks[j, a]
        tj = times[j]
        tj2 = tj * tj
        aj = avar[j]
        yj = y[j]
        okj = ok[j]
        csj = cs[j]
        ncens = False     # an OR, not a count: an int64 counter halves the vector width
        if linear and j == 0:
            # the shortest exposure: nothing to predict from, no censoring
            for i in range(ns):
                raw = np.float32(zr[i])
                yv = raw - dr[i]
                yj[i] = yv
                o = f1 if raw < s else f0
                okj[i] = o
                csj[i] = f0
                sy[i] = o * yv
                st[i] = o * tj
                st2[i] = o * tj2
                sav[i] = o * aj
                nv[i] = o
                nc[i] = f0
            continue
        if linear:
            # the common case in one fused, branch-free loop: the tests below, without
            # the look-up pass that the non-linear path needs first (sharing that path
            # measured 7-8 % slower on the default Poisson merge)
            for i in range(ns):
                raw = np.float32(zr[i])
                d = dr[i]
                yv = raw - d
                yj[i] = yv
                ys = s - d
                o, c = _usable(raw, yv, ys, s, tj, tj2, aj, g32, sy[i], st[i], sav[i])
                csj[i] = ys if c else f0
                ncens = ncens | c
                okj[i] = o
                sy[i] += o * yv
                st[i] += o * tj
                st2[i] += o * tj2
                sav[i] += o * aj
                nv[i] += o
        else:
            lj = lev[j]
            if dark_after:
                zs_ = min(int(s), L - 1)
                for i in range(ns):
                    # (rounded, as the other dark mode does: a float raw DN of 52.7 is
                    # level 53, not 52)
                    zi = min(max(int(np.rint(np.float32(zr[i]))), 0), L - 1)
                    lj[i] = zi
                    yj[i] = elut[cb, zi] - dr[i]
                    ysat[i] = elut[cb, zs_] - dr[i]
            else:
                for i in range(ns):
                    zi = min(max(int(np.rint(np.float32(zr[i]) - dr[i])), 0), L - 1)
                    lj[i] = zi
                    yj[i] = elut[cb, zi]
                    zsi = min(max(int(np.rint(s - dr[i])), 0), L - 1)
                    ysat[i] = elut[cb, zsi]
            for i in range(ns):
                raw = np.float32(zr[i])
                yv = yj[i]
                ys = ysat[i]
                o, c = _usable(raw, yv, ys, s, tj, tj2, aj, g32, sy[i], st[i], sav[i])
                csj[i] = ys if c else f0
                ncens = ncens | c
                okj[i] = o
                sy[i] += o * yv
                st[i] += o * tj
                st2[i] += o * tj2
                sav[i] += o * aj
                nv[i] += o
        if ncens:
            any_cens = True
            for i in range(ns):
                nc[i] += f1 if csj[i] != f0 else f0
    return any_cens


@njit(cache=True, inline="always", error_model="numpy")
def _pool_row(sy, st, nv, X):
    """Pooled (Poisson) estimate ``X = Σy / Σt``; True if some pixel has no usable sample."""
    ns = X.shape[0]
    f0 = np.float32(0.0)
    f1 = np.float32(1.0)
    nbad = False
    for i in range(ns):
        has = nv[i] > f0
        X[i] = sy[i] / (st[i] if has else f1)
        nbad = nbad | (not has)
    return nbad


@njit(cache=True, inline="always", error_model="numpy")
def _fallback_row(zs, l, a, s, times, y, nv, X, nsa, had_bad, nbad):
    """Where no sample is usable (saturated in every exposure): a rare scalar pass.

    ``X`` becomes the shortest exposure's lower bound and ``nsa`` counts the
    saturated exposures; ``nsa`` is reset lazily (``had_bad``: the previous
    band set it). Returns the new ``had_bad``.
    """
    P = len(zs)
    ns = X.shape[0]
    f0 = np.float32(0.0)
    f1 = np.float32(1.0)
    if had_bad:
        for i in range(ns):
            nsa[i] = f0
        had_bad = False
    if nbad:
        had_bad = True
        t0 = times[0]
        for i in range(ns):
            if nv[i] > f0:
                continue
            ns_i = f0
            for j in range(P):
                ns_i += f1 if np.float32(zs[j][l, a, i]) >= s else f0
            nsa[i] = ns_i
            X[i] = y[0, i] / t0          # a lower bound, never extrapolated
    return had_bad


@njit(cache=True, inline="always", error_model="numpy")
def _chi2_sums(times, avar, g32, rel32, ok, y, om, X, sw, swx, swx2):
    """Σw, Σwx and Σwx² of the usable samples ``x = y/t``, ``w = 1/var`` from ``max(X, 0)``.

    The consistency statistic is ``Σw(x − x̄)² = Σwx² − (Σwx)²/Σw`` about the
    inverse-variance mean ``x̄`` (the estimate under which it is χ²-distributed
    with ``n − 1`` dof), taken with weights from the pooled estimate; ``om``
    receives the weights (for the censored residuals).
    """
    P = om.shape[0]
    ns = X.shape[0]
    f0 = np.float32(0.0)
    f1 = np.float32(1.0)
    for j in range(P):
        tj = times[j]
        itj = f1 / tj
        itj2 = itj * itj
        aj = avar[j]
        okj = ok[j]
        yj = y[j]
        omj = om[j]
        if j == 0:
            for i in range(ns):
                xp = max(X[i], f0)
                w = f1 / ((g32 * xp * tj + aj) * itj2 + rel32 * xp * xp)
                omj[i] = w
                wx = okj[i] * w * (yj[i] * itj)
                sw[i] = okj[i] * w
                swx[i] = wx
                swx2[i] = wx * (yj[i] * itj)
        else:
            for i in range(ns):
                xp = max(X[i], f0)
                w = f1 / ((g32 * xp * tj + aj) * itj2 + rel32 * xp * xp)
                omj[i] = w
                wx = okj[i] * w * (yj[i] * itj)
                sw[i] += okj[i] * w
                swx[i] += wx
                swx2[i] += wx * (yj[i] * itj)


@njit(cache=True, inline="always", error_model="numpy")
def _chi2_censored(times, om, cs, sw, swx, swx2):
    """Finish the statistic into ``swx2`` and add the censored residuals (rare).

    A sample that saturated although the others predicted it well below
    saturation (a bright object moved in) adds ``w·(ysat/t − x̄)²``.
    """
    P = om.shape[0]
    ns = sw.shape[0]
    f0 = np.float32(0.0)
    f1 = np.float32(1.0)
    for i in range(ns):
        w = sw[i]
        mean = swx[i] / w if w > f0 else f0
        v = swx2[i] - swx[i] * mean
        swx2[i] = v if v > f0 else f0
        sw[i] = mean
    for j in range(P):
        itj = f1 / times[j]
        csj = cs[j]
        omj = om[j]
        for i in range(ns):
            if csj[i] != f0:
                r = csj[i] * itj - sw[i]
                swx2[i] += omj[i] * r * r if r > f0 else f0


@njit(cache=True, inline="always", error_model="numpy")
def _write_row(X, clip, c, num, den, nv, nsa, P, want_chi2, finished, sw, swx, swx2, nc,
               ol, snr_l, msum_l, nvalid_l, nsat_l, chi2_l, dof_l):
    """Write one band of the output row and accumulate the per-pixel statistics.

    ``X`` is the estimate (a non-finite one is written as 0); the SNR is
    ``max(X, 0)·num/√den`` (``num`` = Σω, ``den`` = Σω²·var of the weights ω).
    With ``want_chi2`` the statistic is ``swx2`` when ``finished``
    (:func:`_chi2_censored` ran), else it is computed here from the sums.    """
    ns = X.shape[0]
    f0 = np.float32(0.0)
    inf32 = np.float32(np.inf)
    fP = np.float32(P)
    two = np.float32(2.0)
    for i in range(ns):
        xi = X[i]
        fin = (xi > -inf32) & (xi < inf32)
        # the output keeps a negative (noise) estimate unless clipped: clipping each
        # one to 0 biases near-zero bands upward, so noise studies may keep them
        x = xi if fin & (xi >= f0) else f0
        xr = xi if fin else f0
        ol[i] = (x if clip else xr) * c
        msum_l[i] += x * c
        has = nv[i] > f0
        nvalid_l[i] += 1 if has else 0
        dn = den[i]
        snr_l[i] += x * num[i] / np.sqrt(dn) if has & (dn > f0) else f0
        nsat_l[i] += 1 if nsa[i] == fP else 0
    if want_chi2 and finished:
        for i in range(ns):
            ne = nv[i] + nc[i]
            m2 = (ne >= two) & (nv[i] > f0)
            chi2_l[i] += swx2[i] if m2 else f0
            dof_l[i] += np.int32(ne) - np.int32(1) if m2 else np.int32(0)
    elif want_chi2:
        for i in range(ns):
            w = sw[i]
            mean = swx[i] / w if w > f0 else f0
            v = swx2[i] - swx[i] * mean
            q = v if v > f0 else f0
            ne = nv[i] + nc[i]
            m2 = (ne >= two) & (nv[i] > f0)
            chi2_l[i] += q if m2 else f0
            dof_l[i] += np.int32(ne) - np.int32(1) if m2 else np.int32(0)
