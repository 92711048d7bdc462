"""The weighted merges of a linear sensor with the χ² ghost statistic of *binned* bands.

Debevec, Robertson and inverse-variance merges test a pixel's consistency as the Poisson
merge does: about the pooled (Poisson) estimate, over the same choice of samples
(:func:`mehs.synthesis._merge_rows._usable`). So the binned statistic of
:mod:`mehs.synthesis._merge_binned` — the χ² of the sums of ``nbin`` adjacent bands, more
power against a moving object's spectrum at ``1/nbin`` of the statistic's divisions —
applies to them unchanged: these kernels are
:mod:`mehs.synthesis._merge_fused_weighted`'s radiance, SNR and outputs, expression for
expression (the same bits), with the Poisson binned kernel's bin bookkeeping and
statistic (:func:`mehs.synthesis._merge_binned._bin_statistic`; its χ² and degrees of
freedom to the bit, tested).

The method's weighted estimate is written out in the sample loop, as in
:func:`mehs.synthesis._merge_fused_weighted._merge_weighted`, not shared with it through an
inline helper returning ``(x, snum, sden)``: with such a helper LLVM kept this kernel's
sample loop scalar at 256-bit vectors (numba's own build, or an AVX2 host: Debevec 193
against 21 ms a 26-line chunk), and it made the per-band Robertson merge 5–9 % slower.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from mehs.synthesis._cephes import expf, logf
from mehs.synthesis._merge_binned import _bin_statistic
from mehs.synthesis._merge_fused_weighted import _method_weight
from mehs.synthesis._merge_rows import DEBEVEC, INVVAR, ROBERTSON, _usable


@njit(cache=True, inline="always", error_model="numpy")
def _merge_weighted_binned(zs, darks, sat, times, L, floor, gain, avar, rel_var, cal, method,
                           clip, nbin, ysum, xps, bms, out, chi2, dof, snr, nsat, nvalid,
                           msum):
    """Debevec / Robertson / inverse-variance merge of a chunk of lines (BIL), linear
    sensor, with the χ² of bins of ``nbin`` adjacent bands (the last bin may be shorter).

    Arguments as :func:`mehs.synthesis._merge_fused_weighted._merge_weighted` without
    ``want_chi2`` (this is the statistic's kernel), plus ``nbin`` and the scratch of
    :func:`mehs.synthesis._merge_binned.merge_chunk_poisson_linear_binned` (at most 16
    exposures). ``method`` a compile-time constant.
    """
    P = len(zs)
    nl, nb, ns = out.shape
    f0 = np.float32(0.0)
    f1 = np.float32(1.0)
    top = np.float32(L - 1)
    hmid = np.float32((L - 1) / 2.0)
    fl = np.float32(floor)
    g32 = np.float32(gain)
    rel32 = np.float32(rel_var)
    inf32 = np.float32(np.inf)
    fP = np.float32(P)
    half = np.float32(0.5)
    deb = method == DEBEVEC
    for l in range(nl):
        ol_ = out[l]
        snr_l, msum_l, nvalid_l, nsat_l = snr[l], msum[l], nvalid[l], nsat[l]
        chi2_l, dof_l = chi2[l], dof[l]
        for a0 in range(0, nb, nbin):
            kb = min(nbin, nb - a0)
            for b in range(kb):
                a = a0 + b
                first = b == 0
                s = sat[a]
                c_a = cal[a]
                ol = ol_[a]
                for i in range(ns):
                    # -- choose the samples (merge_chunk_poisson_linear_binned's loop)
                    sy = f0
                    st = f0
                    st2 = f0
                    sav = f0
                    nv = f0
                    nsc = f0
                    okm = 0
                    cm = 0
                    for j in range(P):
                        r_ = np.float32(zs[j][l, a, i])
                        d = darks[j, a, i]
                        tj = times[j]
                        tj2 = tj * tj
                        aj = avar[j]
                        yv = r_ - d
                        ys = s - d
                        nsc += f1 if r_ >= s else f0
                        if j == 0:
                            o = f1 if r_ < s else f0
                            sy = o * yv
                            st = o * tj
                            st2 = o * tj2
                            sav = o * aj
                            nv = o
                        else:
                            o, c = _usable(r_, yv, ys, s, tj, tj2, aj, g32, sy, st, sav)
                            cb = c & (ys != f0)
                            cm |= (1 << j) if cb else 0
                            sy += o * yv
                            st += o * tj
                            st2 += o * tj2
                            sav += o * aj
                            nv += o
                        okm |= (1 << j) if o != f0 else 0
                        ysum[j][i] = (f0 if first else ysum[j][i]) + (yv if o != f0 else ys)
                    # -- the pooled (Poisson) estimate, or the shortest exposure's lower bound
                    has = nv > f0
                    xi = sy / (st if has else f1)
                    nsa = f0
                    if not has:
                        nsa = nsc
                        xi = (np.float32(zs[0][l, a, i]) - darks[0, a, i]) / times[0]
                    xp = max(xi, f0)
                    # -- the method's weighted estimate and its SNR (_merge_weighted's)
                    num = f0
                    den = f0
                    s1 = f0
                    s2 = f0
                    s3 = f0
                    for j in range(P):
                        tj = times[j]
                        okj = f1 if (okm >> j) & 1 else f0
                        yj = np.float32(zs[j][l, a, i]) - darks[j, a, i]
                        w = _method_weight(method, okj, yj, xp, tj, avar[j], g32, top, hmid, fl)
                        if deb:
                            # g(y) = ln y of the fractional y = raw − dark (see _merge_weighted)
                            num += w * (logf(max(yj, half)) - np.float32(np.log(tj)))
                        else:
                            num += w * yj / tj
                        den += w
                        if deb:
                            r = w / tj
                            s1 += okj * w * r
                            s2 += okj * r * r * avar[j]
                            s3 += okj * w * w
                    if deb:
                        q = num / den if den > f0 else f0
                        xe = expf(q)
                        xm = xe if den > f0 else xi
                    else:
                        xw = num / (den if den > f0 else f1)
                        xm = xw if den > f0 else xi
                    # usable samples all with zero level weight: the pooled weights ω = t
                    pooled_w = (method == DEBEVEC or method == ROBERTSON) & (den == f0) & has
                    x = xm if (xm >= f0) & (xm < inf32) else f0
                    if deb:
                        snum = st if pooled_w else den
                        sden = (g32 * x * (st if pooled_w else s1) + (sav if pooled_w else s2)
                                + rel32 * x * x * (st2 if pooled_w else s3))
                    else:
                        snum = f0
                        sden = f0
                        for j in range(P):
                            tj = times[j]
                            aj = avar[j]
                            okj = f1 if (okm >> j) & 1 else f0
                            yj = np.float32(zs[j][l, a, i]) - darks[j, a, i]
                            w = (okj * tj if pooled_w
                                 else _method_weight(method, okj, yj, xp, tj, aj, g32, top,
                                                     hmid, fl))
                            v = (g32 * x * tj + aj) / (tj * tj) + rel32 * x * x
                            snum += okj * w
                            sden += okj * w * w * v
                    # -- write (the stage kernel's _write_row)
                    fin = (xm > -inf32) & (xm < inf32)
                    xo = xm if fin & (xm >= f0) else f0
                    xr = xm if fin else f0
                    ol[i] = (xo if clip else xr) * c_a
                    msum_l[i] += xo * c_a
                    nvalid_l[i] += 1 if has else 0
                    snr_l[i] += xo * snum / np.sqrt(sden) if has & (sden > f0) else f0
                    nsat_l[i] += 1 if nsa == fP else 0
                    # -- the bin's running estimate and exposure masks
                    xps[i] = (f0 if first else xps[i]) + xp
                    m = okm | ((okm | cm) << 16)
                    bms[i] = m if first else (bms[i] & m)
            _bin_statistic(ysum, xps, bms, times, avar, g32, rel32, np.float32(kb), chi2_l,
                           dof_l)


@njit(nogil=True, cache=True, error_model="numpy")
def merge_chunk_debevec_linear_binned(zs, darks, sat, times, L, floor, gain, avar, rel_var,
                                      cal, want_chi2, clip, nbin, ysum, xps, bms, out, chi2,
                                      dof, snr, nsat, nvalid, msum):
    """Debevec & Malik's log-domain mean with the binned χ² (see
    :func:`_merge_weighted_binned`; ``want_chi2`` is ignored)."""
    _merge_weighted_binned(zs, darks, sat, times, L, floor, gain, avar, rel_var, cal, DEBEVEC,
                           clip, nbin, ysum, xps, bms, out, chi2, dof, snr, nsat, nvalid, msum)


@njit(nogil=True, cache=True, error_model="numpy")
def merge_chunk_robertson_linear_binned(zs, darks, sat, times, L, floor, gain, avar, rel_var,
                                        cal, want_chi2, clip, nbin, ysum, xps, bms, out, chi2,
                                        dof, snr, nsat, nvalid, msum):
    """Robertson et al.'s ``w·t²``-weighted mean with the binned χ² (see
    :func:`_merge_weighted_binned`; ``want_chi2`` is ignored)."""
    _merge_weighted_binned(zs, darks, sat, times, L, floor, gain, avar, rel_var, cal,
                           ROBERTSON, clip, nbin, ysum, xps, bms, out, chi2, dof, snr, nsat,
                           nvalid, msum)


@njit(nogil=True, cache=True, error_model="numpy")
def merge_chunk_invvar_linear_binned(zs, darks, sat, times, L, floor, gain, avar, rel_var,
                                     cal, want_chi2, clip, nbin, ysum, xps, bms, out, chi2,
                                     dof, snr, nsat, nvalid, msum):
    """Inverse-variance weights with the binned χ² (see :func:`_merge_weighted_binned`;
    ``want_chi2`` is ignored)."""
    _merge_weighted_binned(zs, darks, sat, times, L, floor, gain, avar, rel_var, cal, INVVAR,
                           clip, nbin, ysum, xps, bms, out, chi2, dof, snr, nsat, nvalid, msum)
