"""Compiled (numba) inner loops of the synthesis stage.

Kept apart from the public modules so that importing :mod:`mehs.synthesis`
stays cheap; numba compiles these on first use and caches the machine code
(``cache=True``). ``fastmath`` stays off: the merge must give the same numbers
as the reference formulas, and NaN/inf checks must not be optimised away.
"""

from __future__ import annotations

import numpy as np
from numba import njit, prange

# Merge method codes shared with mehs.synthesis.merge.
DEBEVEC, ROBERTSON, POISSON, INVVAR = 0, 1, 2, 3


# ---------------------------------------------------------------- response solve
@njit(cache=True)
def _penta_factor(c, wsm, lam, mid, d, l1, l2):
    """LDLᵀ of ``M = diag(c) + λ D2ᵀ diag(wsm²) D2`` with row/column ``mid`` fixed.

    ``d`` (diagonal), ``l1``/``l2`` (first/second sub-diagonal of L) are written
    in place. M is pentadiagonal, so the factorisation costs O(levels).
    """
    n = c.shape[0]
    d0 = c.copy()
    d1 = np.zeros(n)
    d2 = np.zeros(n)
    for k in range(1, n - 1):
        s = lam * wsm[k] * wsm[k]
        d0[k - 1] += s
        d0[k] += 4.0 * s
        d0[k + 1] += s
        d1[k - 1] -= 2.0 * s
        d1[k] -= 2.0 * s
        d2[k - 1] += s
    # The gauge level is known: its row and column become the identity.
    d0[mid] = 1.0
    d1[mid] = 0.0
    d2[mid] = 0.0
    if mid >= 1:
        d1[mid - 1] = 0.0
    if mid >= 2:
        d2[mid - 2] = 0.0
    for i in range(n):
        di = d0[i]
        if i >= 1:
            di -= l1[i - 1] * l1[i - 1] * d[i - 1]
        if i >= 2:
            di -= l2[i - 2] * l2[i - 2] * d[i - 2]
        if di <= 0.0:
            di = 1e-300
        d[i] = di
        v = d1[i]
        if i >= 1:
            v -= l2[i - 1] * d[i - 1] * l1[i - 1]
        l1[i] = v / di
        l2[i] = d2[i] / di


@njit(cache=True)
def _penta_solve(d, l1, l2, r, out):
    n = d.shape[0]
    for i in range(n):
        v = r[i]
        if i >= 1:
            v -= l1[i - 1] * out[i - 1]
        if i >= 2:
            v -= l2[i - 2] * out[i - 2]
        out[i] = v
    for i in range(n):
        out[i] /= d[i]
    for i in range(n - 1, -1, -1):
        v = out[i]
        if i + 1 < n:
            v -= l1[i] * out[i + 1]
        if i + 2 < n:
            v -= l2[i] * out[i + 2]
        out[i] = v


@njit(cache=True)
def _schur_matvec(x, c, wsm, lam, Z, w2, Winv, mid, y):
    """``y = S x``: the Debevec normal equations with every ln E_i eliminated."""
    n = c.shape[0]
    for i in range(n):
        y[i] = c[i] * x[i]
    for k in range(1, n - 1):
        s = lam * wsm[k] * wsm[k] * (x[k - 1] - 2.0 * x[k] + x[k + 1])
        y[k - 1] += s
        y[k] -= 2.0 * s
        y[k + 1] += s
    npix, P = Z.shape
    for i in range(npix):
        if Winv[i] == 0.0:
            continue
        dot = 0.0
        for j in range(P):
            dot += w2[i, j] * x[Z[i, j]]
        dot *= Winv[i]
        for j in range(P):
            y[Z[i, j]] -= w2[i, j] * dot
    y[mid] = 0.0


@njit(parallel=True, cache=True)
def debevec_pcg(Z, wz, logt, wsm, lam, mid, tol, maxiter):
    """Solve the Debevec–Malik system of each channel by preconditioned CG.

    Parameters
    ----------
    Z : int32 (C, N, P)
        Sampled levels per channel, pixel and exposure.
    wz : float64 (C, N, P)
        Data weights ``w(Z)`` (0 for saturated / unusable samples).
    logt : float64 (1, 1, P) or (C, N, P)
        ln of the exposure times, or one effective log time per sample
        (``ln(t_j + B_ij/E_i)`` for an offset ``B`` passed through the response).
    wsm : float64 (L,)
        Weights of the smoothness rows.
    lam : float64 (C,)
        Effective smoothness per channel.
    mid : int
        Gauge level (its g is fixed to 0 here; the caller shifts it).

    Returns
    -------
    g : float64 (C, L); iterations : int64 (C,); relative residual : float64 (C,)

    The ln E unknowns are eliminated exactly (one per pixel, block-diagonal),
    leaving the L×L Schur complement ``S``; it is solved by CG preconditioned
    with its pentadiagonal part (data diagonal + smoothness), factorised in O(L).
    """
    C, N, P = Z.shape
    L = wsm.shape[0]
    g = np.zeros((C, L))
    iters = np.zeros(C, dtype=np.int64)
    relres = np.zeros(C)
    for ch in prange(C):
        Zc = Z[ch]
        w2 = wz[ch] * wz[ch]
        Winv = np.zeros(N)
        c = np.zeros(L)
        b = np.zeros(L)
        per_sample = logt.shape[1] > 1
        for i in range(N):
            W = 0.0
            m = 0.0
            for j in range(P):
                lt = logt[ch, i, j] if per_sample else logt[0, 0, j]
                W += w2[i, j]
                m += w2[i, j] * lt
            if W > 0.0:
                Winv[i] = 1.0 / W
                m /= W
                for j in range(P):
                    lt = logt[ch, i, j] if per_sample else logt[0, 0, j]
                    c[Zc[i, j]] += w2[i, j]
                    b[Zc[i, j]] += w2[i, j] * (lt - m)
        b[mid] = 0.0
        d = np.zeros(L)
        l1 = np.zeros(L)
        l2 = np.zeros(L)
        _penta_factor(c, wsm, lam[ch], mid, d, l1, l2)
        x = np.zeros(L)
        r = b.copy()
        zv = np.zeros(L)
        _penta_solve(d, l1, l2, r, zv)
        zv[mid] = 0.0
        p = zv.copy()
        q = np.zeros(L)
        rz = 0.0
        bn = 0.0
        for i in range(L):
            rz += r[i] * zv[i]
            bn += b[i] * b[i]
        bn = np.sqrt(bn)
        it = 0
        rn = bn
        if bn > 0.0:
            while it < maxiter:
                _schur_matvec(p, c, wsm, lam[ch], Zc, w2, Winv, mid, q)
                pq = 0.0
                for i in range(L):
                    pq += p[i] * q[i]
                if pq <= 0.0:
                    break
                alpha = rz / pq
                rn = 0.0
                for i in range(L):
                    x[i] += alpha * p[i]
                    r[i] -= alpha * q[i]
                    rn += r[i] * r[i]
                rn = np.sqrt(rn)
                it += 1
                if rn <= tol * bn:
                    break
                _penta_solve(d, l1, l2, r, zv)
                zv[mid] = 0.0
                rz_new = 0.0
                for i in range(L):
                    rz_new += r[i] * zv[i]
                beta = rz_new / rz
                rz = rz_new
                for i in range(L):
                    p[i] = zv[i] + beta * p[i]
        for i in range(L):
            g[ch, i] = x[i]
        iters[ch] = it
        relres[ch] = rn / bn if bn > 0.0 else 0.0
    return g, iters, relres


@njit(parallel=True, cache=True)
def stratified_pick(levels, order, n, strata, L):
    """Pick up to ``n`` pixels per channel, stratified over exposures × intensity.

    ``levels`` int32 (P, M, C) holds candidate levels (L-1 marks saturated);
    pixels are visited in the random ``order`` and kept while any of their
    exposures falls in an under-filled (exposure, stratum) cell. Only pixels
    with at least two usable exposures (0 < level < L-1) are eligible, since a
    pixel seen once carries no information about g. Returns int64 (C, n)
    candidate indices, −1 where fewer eligible pixels exist.
    """
    P, M, C = levels.shape
    K = order.shape[0]
    quota = (n + P * strata - 1) // (P * strata)
    out = -np.ones((C, n), dtype=np.int64)
    for ch in prange(C):
        count = np.zeros((P, strata), dtype=np.int64)
        picked = np.zeros(K, dtype=np.bool_)   # the second pass must not repeat a pixel
        taken = 0
        for pass_ in range(2):
            if taken >= n:
                break
            for k in range(K):
                if taken >= n:
                    break
                i = order[k]
                usable = 0
                want = False
                for j in range(P):
                    z = levels[j, i, ch]
                    if z > 0 and z < L - 1:
                        usable += 1
                        s = z * strata // L
                        if count[j, s] < quota:
                            want = True
                if usable < 2:
                    continue
                if pass_ == 0 and not want:
                    continue
                if picked[k]:
                    continue
                picked[k] = True
                out[ch, taken] = i
                taken += 1
                for j in range(P):
                    z = levels[j, i, ch]
                    if z > 0 and z < L - 1:
                        count[j, z * strata // L] += 1
    return out


# ------------------------------------------------------------------------ merge
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


@njit(parallel=True, cache=True)
def merge_chunk(zs, darks, sat, times, linear, dark_after, glut, elut, wlut,
                floor, gain, avar, rel_var, cal, method, want_chi2,
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
        DEBEVEC, ROBERTSON, POISSON or INVVAR.
    want_chi2 : bool
        Accumulate the ghost statistic.

    Outputs (written in place): ``out`` float32 (lines, bands, samples);
    per pixel (lines, samples): ``chi2`` float32 consistency statistic,
    ``dof`` int32, ``snr`` float32 (summed over bands), ``nsat`` int32 bands
    saturated in every exposure, ``nvalid`` int32 bands with a usable sample,
    ``msum`` float32 sum over bands of the output.

    Sample selection avoids the sample's own noise (which would bias the
    per-exposure estimates and the consistency test): every unsaturated sample
    is used by the linear estimators, and exposure j ≥ 1 where the running
    Poisson estimate of the shorter exposures predicts it ``3σ`` below
    saturation — or, where that prediction is more than twice as noisy as the
    sample (brackets ×50–×200 apart, dark bands), where the sample itself lies
    ``3σ`` below saturation: deciding by a much noisier prediction dropped the
    long sample exactly where the short one had noise up, +15 % at 400 nm. ``χ²`` is taken about the inverse-variance mean of the usable
    samples (the estimate under which it is χ²-distributed with ``n − 1`` dof),
    plus censored residuals of samples that saturated against a confident
    prediction (a bright object moved in).

    Every inner loop runs over the contiguous samples axis with selects only,
    so LLVM vectorises it; the exposures and bands are the outer loops and the
    per-row scratch lives in L1.
    """
    P = len(zs)
    nl, nb, ns = out.shape
    L = wlut.shape[0]
    shared = glut.shape[0] == 1
    f0 = np.float32(0.0)
    f1 = np.float32(1.0)
    g32 = np.float32(gain)
    rel32 = np.float32(rel_var)
    fl = np.float32(floor)
    k2u = ROOM_SIGMA2
    k2c = CENSOR_SIGMA2
    k2p = PREDICTION_NOISIER2
    for l in prange(nl):
        y = np.empty((P, ns), dtype=np.float32)
        ok = np.empty((P, ns), dtype=np.float32)
        om = np.empty((P, ns), dtype=np.float32)
        cs = np.empty((P, ns), dtype=np.float32)
        lev = np.zeros((P, ns), dtype=np.int32)
        sy = np.empty(ns, dtype=np.float32)
        st = np.empty(ns, dtype=np.float32)
        sav = np.empty(ns, dtype=np.float32)
        nv = np.empty(ns, dtype=np.float32)
        nc = np.empty(ns, dtype=np.float32)
        nsa = np.empty(ns, dtype=np.float32)
        st2 = np.empty(ns, dtype=np.float32)
        X = np.empty(ns, dtype=np.float32)
        XR = np.empty(ns, dtype=np.float32)
        XP = np.empty(ns, dtype=np.float32)
        num = np.empty(ns, dtype=np.float32)
        den = np.empty(ns, dtype=np.float32)
        ysat = np.empty(ns, dtype=np.float32)
        for i in range(ns):
            nsa[i] = f0
        had_bad = False
        for a in range(nb):
            cb = 0 if shared else a
            s = sat[a]
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
                ncens = 0
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
                elif linear:
                    # the common case in one fused, branch-free loop
                    for i in range(ns):
                        raw = np.float32(zr[i])
                        d = dr[i]
                        yv = raw - d
                        yj[i] = yv
                        ys = s - d
                        sti = st[i]
                        syi = max(sy[i], f0)
                        # (ysat − predicted y)·Σt and the prediction's variance·(Σt)²
                        room = ys * sti - syi * tj
                        vp = g32 * syi * tj * sti + aj * sti * sti + tj2 * (g32 * syi + sav[i])
                        r2 = room * room
                        pos = room > f0
                        unsat = raw < s
                        # a prediction from exposures ×50–×200 shorter is far noisier than
                        # the sample itself: then its own 3σ margin below saturation decides
                        # (a bias confined to a 3σ band under saturation, instead of dropping
                        # every long sample whose short prediction happened to be high)
                        vown = g32 * max(ys, f0) + aj
                        marg = ys - yv
                        own = (vp > k2p * vown * sti * sti) & (marg > f0) & (marg * marg > k2u * vown)
                        o = f1 if unsat & ((sti == f0) | (pos & (r2 > k2u * vp)) | own) else f0
                        c = (raw >= s) & (sti > f0) & pos & (r2 > k2c * vp)
                        csj[i] = ys if c else f0
                        ncens += 1 if c else 0
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
                            zi = min(int(zr[i]), L - 1)
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
                        sti = st[i]
                        syi = max(sy[i], f0)
                        room = ys * sti - syi * tj
                        vp = g32 * syi * tj * sti + aj * sti * sti + tj2 * (g32 * syi + sav[i])
                        r2 = room * room
                        pos = room > f0
                        unsat = raw < s
                        # a prediction from exposures ×50–×200 shorter is far noisier than
                        # the sample itself: then its own 3σ margin below saturation decides
                        # (a bias confined to a 3σ band under saturation, instead of dropping
                        # every long sample whose short prediction happened to be high)
                        vown = g32 * max(ys, f0) + aj
                        marg = ys - yv
                        own = (vp > k2p * vown * sti * sti) & (marg > f0) & (marg * marg > k2u * vown)
                        o = f1 if unsat & ((sti == f0) | (pos & (r2 > k2u * vp)) | own) else f0
                        c = (raw >= s) & (sti > f0) & pos & (r2 > k2c * vp)
                        csj[i] = ys if c else f0
                        ncens += 1 if c else 0
                        okj[i] = o
                        sy[i] += o * yv
                        st[i] += o * tj
                        st2[i] += o * tj2
                        sav[i] += o * aj
                        nv[i] += o
                if ncens > 0:
                    any_cens = True
                    for i in range(ns):
                        nc[i] += f1 if csj[i] != f0 else f0
            # pooled (Poisson) estimate, branch-free; fall-backs in a rare scalar pass
            nbad = 0
            for i in range(ns):
                has = nv[i] > f0
                X[i] = sy[i] / (st[i] if has else f1)
                nbad += 0 if has else 1
            if had_bad:
                for i in range(ns):
                    nsa[i] = f0
                had_bad = False
            if nbad > 0:
                # rare: no usable sample (saturated in every exposure) somewhere in
                # this row; the saturation flags are derived here, not in the hot loop
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
            for i in range(ns):
                XP[i] = max(X[i], f0)
            if method != POISSON:
                # (Poisson's weights are t_j: its SNR comes from the running sums)
                for i in range(ns):
                    num[i] = f0
                    den[i] = f0
                for j in range(P):
                    tj = times[j]
                    aj = avar[j]
                    lt = np.float32(np.log(tj))
                    okj = ok[j]
                    yj = y[j]
                    omj = om[j]
                    if method == INVVAR:
                        # variance predicted from the pooled estimate, not from y_j
                        # itself (which would give low samples more weight: biased)
                        for i in range(ns):
                            w = okj[i] * tj * tj / (g32 * XP[i] * tj + aj)
                            omj[i] = w
                            num[i] += w * yj[i] / tj
                            den[i] += w
                    elif method == ROBERTSON:
                        lj = lev[j]
                        if linear:
                            # the level weight of the *expected* level X·t: the
                            # sample's own level would favour upward noise (bias)
                            for i in range(ns):
                                lj[i] = min(max(int(XP[i] * tj + np.float32(0.5)), 0), L - 1)
                        for i in range(ns):
                            w = okj[i] * wlut[lj[i]] * tj * tj
                            omj[i] = w
                            num[i] += w * yj[i] / tj
                            den[i] += w
                    else:
                        lj = lev[j]
                        if linear:
                            for i in range(ns):
                                lj[i] = min(max(int(yj[i] + np.float32(0.5)), 0), L - 1)
                        if dark_after:
                            for i in range(ns):
                                w = okj[i] * wlut[lj[i]] if yj[i] > fl else f0
                                omj[i] = w
                                if w > f0:
                                    num[i] += w * (np.log(yj[i]) - lt)
                                    den[i] += w
                        else:
                            # Debevec's own form: g of the integer level (ln z for a
                            # linear sensor), a table look-up, no per-sample log
                            gl = glut[cb]
                            for i in range(ns):
                                w = okj[i] * wlut[lj[i]] if yj[i] > fl else f0
                                omj[i] = w
                                num[i] += w * (gl[lj[i]] - lt)
                                den[i] += w
                for i in range(ns):
                    if den[i] > f0:
                        X[i] = np.exp(num[i] / den[i]) if method == DEBEVEC else num[i] / den[i]
                if method == DEBEVEC or method == ROBERTSON:
                    for i in range(ns):
                        if den[i] == f0 and nv[i] > f0:
                            # usable samples, all with zero level weight: pooled estimate
                            for j in range(P):
                                om[j, i] = ok[j, i] * times[j]
            # noise-model SNR and the consistency statistic
            inf32 = np.float32(np.inf)
            for i in range(ns):
                xi = X[i]
                # the output keeps a negative (noise) estimate: clipping each one to 0
                # biases near-zero bands upward; the noise model below uses max(X, 0)
                XR[i] = xi if (xi > -inf32) & (xi < inf32) else f0
                X[i] = xi if (xi >= f0) & (xi < inf32) else f0
            if method == POISSON:
                # Σω = Σt, Σω²var = gain·X·Σt + Σa + rel·X²·Σt²: no per-sample pass
                for i in range(ns):
                    num[i] = st[i]
                    den[i] = g32 * X[i] * st[i] + sav[i] + rel32 * X[i] * X[i] * st2[i]
            else:
                for i in range(ns):
                    num[i] = f0
                    den[i] = f0
                for j in range(P):
                    tj = times[j]
                    aj = avar[j]
                    okj = ok[j]
                    omj = om[j]
                    for i in range(ns):
                        v = (g32 * X[i] * tj + aj) / (tj * tj) + rel32 * X[i] * X[i]
                        num[i] += okj[i] * omj[i]
                        den[i] += okj[i] * omj[i] * omj[i] * v
            if want_chi2:
                # χ² about the inverse-variance mean in one pass:
                # Σw(x − x̄)² = Σwx² − (Σwx)²/Σw, with w = 1/var from the pooled estimate
                for i in range(ns):
                    sy[i] = f0
                    st[i] = f0
                    st2[i] = f0
                for j in range(P):
                    tj = times[j]
                    itj = f1 / tj
                    itj2 = itj * itj
                    aj = avar[j]
                    okj = ok[j]
                    yj = y[j]
                    omj = om[j]
                    for i in range(ns):
                        xp = XP[i]
                        w = f1 / ((g32 * xp * tj + aj) * itj2 + rel32 * xp * xp)
                        omj[i] = w
                        wx = okj[i] * w * (yj[i] * itj)
                        st[i] += okj[i] * w
                        sy[i] += wx
                        st2[i] += wx * (yj[i] * itj)
                for i in range(ns):
                    sti = st[i]
                    has = sti > f0
                    XP[i] = sy[i] / sti if has else f0
                    q = st2[i] - sy[i] * XP[i]
                    sy[i] = q if q > f0 else f0
                if any_cens:
                    for j in range(P):
                        itj = f1 / times[j]
                        csj = cs[j]
                        omj = om[j]
                        for i in range(ns):
                            if csj[i] != f0:
                                r = csj[i] * itj - XP[i]
                                sy[i] += omj[i] * r * r if r > f0 else f0
            c = cal[a]
            ol = out[l, a]
            snr_l = snr[l]
            msum_l = msum[l]
            nvalid_l = nvalid[l]
            nsat_l = nsat[l]
            chi2_l = chi2[l]
            dof_l = dof[l]
            fP = np.float32(P)
            two = np.float32(2.0)
            for i in range(ns):
                xi = X[i]
                ol[i] = XR[i] * c
                msum_l[i] += xi * c
                has = nv[i] > f0
                nvalid_l[i] += 1 if has else 0
                dn = den[i]
                snr_l[i] += xi * num[i] / np.sqrt(dn) if has & (dn > f0) else f0
                nsat_l[i] += 1 if nsa[i] == fP else 0
            if want_chi2:
                for i in range(ns):
                    ne = nv[i] + nc[i]
                    m2 = (ne >= two) & (nv[i] > f0)
                    chi2_l[i] += sy[i] if m2 else f0
                    dof_l[i] += int(ne) - 1 if m2 else 0


# a first-ever run compiles for 10-20 s: say so instead of looking hung (issue 16)
from mehs.synthesis._numba_cache import notice_if_uncached  # noqa: E402

notice_if_uncached(merge_chunk)
