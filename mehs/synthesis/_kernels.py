"""Compiled (numba) inner loops of response recovery (the merge: :mod:`._merge_kernels`).

Kept apart from the public modules so that importing :mod:`mehs.synthesis`
stays cheap; numba compiles these on first use and caches the machine code
(``cache=True``). ``fastmath`` stays off: the merge must give the same numbers
as the reference formulas, and NaN/inf checks must not be optimised away.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from mehs.synthesis._numba_cache import ensure_cache_locator, notice_if_uncached
from mehs.synthesis._ranges import run_ranges

# before the first cache=True decorator: numba refuses one it has nowhere to cache
ensure_cache_locator()

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


@njit(nogil=True, cache=True)
def _debevec_pcg_range(Z, wz, logt, wsm, lam, mid, tol, maxiter, c0, c1, g, iters, relres):
    """Solve the Debevec–Malik system of channels ``c0``..``c1 − 1`` by preconditioned CG.

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

    Writes ``g`` float64 (C, L), ``iters`` int64 (C,) and ``relres`` float64 (C,)
    (relative residual) of those channels.

    The ln E unknowns are eliminated exactly (one per pixel, block-diagonal),
    leaving the L×L Schur complement ``S``; it is solved by CG preconditioned
    with its pentadiagonal part (data diagonal + smoothness), factorised in O(L).
    """
    N = Z.shape[1]
    P = Z.shape[2]
    L = wsm.shape[0]
    for ch in range(c0, c1):
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


@njit(nogil=True, cache=True)
def _stratified_pick_range(levels, order, n, strata, L, c0, c1, out):
    """Pick up to ``n`` pixels per channel, stratified over exposures × intensity.

    ``levels`` int32 (P, M, C) holds candidate levels (L-1 marks saturated);
    pixels are visited in the random ``order`` and kept while any of their
    exposures falls in an under-filled (exposure, stratum) cell. Only pixels
    with at least two usable exposures (0 < level < L-1) are eligible, since a
    pixel seen once carries no information about g. Writes channels
    ``c0``..``c1 − 1`` of ``out`` int64 (C, n): candidate indices, −1 where
    fewer eligible pixels exist.
    """
    P = levels.shape[0]
    K = order.shape[0]
    quota = (n + P * strata - 1) // (P * strata)
    for ch in range(c0, c1):
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


def debevec_pcg(Z, wz, logt, wsm, lam, mid, tol, maxiter):
    """Solve the Debevec–Malik system of each channel by preconditioned CG.

    Arguments as :func:`_debevec_pcg_range` (``Z`` int32 (C, N, P), ``wz`` float64
    (C, N, P), ``logt`` float64 (1, 1, P) or (C, N, P), ``wsm`` (L,), ``lam`` (C,)).
    Returns ``g`` float64 (C, L), iterations int64 (C,), relative residual float64 (C,).
    """
    C = Z.shape[0]
    L = wsm.shape[0]
    g = np.zeros((C, L))
    iters = np.zeros(C, dtype=np.int64)
    relres = np.zeros(C)
    # serial kernels on channel ranges: parfor compiled for 11-20 s of a first-ever run
    # and gains nothing for the default shared curve (one channel)
    run_ranges(C, lambda c0, c1: _debevec_pcg_range(Z, wz, logt, wsm, lam, mid, tol, maxiter,
                                                     c0, c1, g, iters, relres),
               name="mehs-response")
    return g, iters, relres


def stratified_pick(levels, order, n, strata, L):
    """Pick up to ``n`` pixels per channel, stratified over exposures × intensity.

    ``levels`` int32 (P, M, C); returns int64 (C, n) candidate indices, −1 where
    fewer eligible pixels exist. See :func:`_stratified_pick_range`.
    """
    C = levels.shape[2]
    out = -np.ones((C, n), dtype=np.int64)
    run_ranges(C, lambda c0, c1: _stratified_pick_range(levels, order, n, strata, L, c0, c1,
                                                        out), name="mehs-response")
    return out


# a first-ever run compiles for seconds: say so instead of looking hung (issue 16)
notice_if_uncached(_debevec_pcg_range, "the synthesis kernels")
