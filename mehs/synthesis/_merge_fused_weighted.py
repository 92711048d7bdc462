"""Debevec, Robertson and inverse-variance merges of a linear sensor in one pass per sample.

The weighted methods' stage kernel (:func:`mehs.synthesis._merge_kernels.merge_chunk`)
makes about a dozen passes over each row — selection, pooled estimate, one per
exposure for the method's weights (and a vectorised ``ln`` pass for Debevec), the
``exp`` pass, the SNR and consistency passes — through per-row scratch arrays.
Here, as in :mod:`mehs.synthesis._merge_fused` for the Poisson merge, the
exposures are the unrolled inner loop of each sample and the running sums stay in
registers; ``ln`` and ``exp`` are the scalar Cephes forms of
:mod:`mehs.synthesis._cephes`, so the sample loop still vectorises.

It covers the common case: a linear response (``g(y) = ln y`` of the fractional
``y = raw − dark``) and Debevec's hat weighting, computed rather than looked up (a
look-up per sample is a gather).
Any other curve or weighting keeps the stage kernel.

The arithmetic is the stage kernel's expression for expression, in the same order,
so the numbers are the same to the bit (tested). The choice of each exposure and the
consistency statistic are the helpers the Poisson kernel uses
(:func:`mehs.synthesis._merge_rows._usable`, :func:`mehs.synthesis._merge_fused._consistency`),
inlined by numba.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from mehs.synthesis._cephes import expf, logf
from mehs.synthesis._merge_fused import _consistency
from mehs.synthesis._merge_rows import DEBEVEC, INVVAR, ROBERTSON, _usable


@njit(cache=True, inline="always", error_model="numpy")
def _level(v, top):
    """The integer level of ``v`` (rounded, clipped to ``[0, top]``), as float32."""
    return np.float32(np.int32(min(max(v + np.float32(0.5), np.float32(0.0)), top)))


@njit(cache=True, inline="always", error_model="numpy")
def _method_weight(method, okj, yj, xp, tj, aj, g32, top, hmid, fl):
    """The stage kernel's weight of sample ``j`` (usable: ``okj`` = 1) for ``method``.

    Debevec: the hat of the sample's fractional level ``y`` (the ``z`` of ``g(z) = ln z``),
    zero at or below the floor (``ln y`` needs ``y > 0``); Robertson: the hat of the
    *expected* level ``X·t`` (the sample's own would favour upward noise) times ``t²``;
    inverse variance: ``t² / var(X·t)``.
    """
    if method == DEBEVEC:
        lvi = min(max(yj, np.float32(0.0)), top)
        w = okj * (min(lvi, top - lvi) / hmid)
        return w if yj > fl else np.float32(0.0)
    if method == ROBERTSON:
        lvi = _level(xp * tj, top)
        return okj * (min(lvi, top - lvi) / hmid) * tj * tj
    return okj * tj * tj / (g32 * xp * tj + aj)


@njit(cache=True, inline="always", error_model="numpy")
def _merge_weighted(zs, darks, sat, times, L, floor, gain, avar, rel_var, cal, method,
                    want_chi2, clip, out, chi2, dof, snr, nsat, nvalid, msum):
    """Debevec / Robertson / inverse-variance merge of a chunk of lines (BIL), linear sensor.

    Arguments as :func:`mehs.synthesis._merge_kernels.merge_chunk` for a linear curve
    and the hat weighting (``L`` levels), without the look-up tables. ``method`` must
    be a compile-time constant (one entry point per method below): a run-time branch
    between the methods inside the sample loop kept it from vectorising (7× slower).
    """
    P = len(zs)
    nl, nb, ns = out.shape
    f0 = np.float32(0.0)
    f1 = np.float32(1.0)
    half = np.float32(0.5)
    top = np.float32(L - 1)
    hmid = np.float32((L - 1) / 2.0)
    fl = np.float32(floor)
    g32 = np.float32(gain)
    rel32 = np.float32(rel_var)
    inf32 = np.float32(np.inf)
    fP = np.float32(P)
    two = np.float32(2.0)
    deb = method == DEBEVEC
    for l in range(nl):
        ol_ = out[l]
        snr_l, msum_l, nvalid_l, nsat_l = snr[l], msum[l], nvalid[l], nsat[l]
        chi2_l, dof_l = chi2[l], dof[l]
        for a in range(nb):
            s = sat[a]
            c_a = cal[a]
            ol = ol_[a]
            for i in range(ns):
                # -- choose the samples (as merge_chunk_poisson_linear)
                sy = f0
                st = f0
                st2 = f0
                sav = f0
                nv = f0
                nc = f0
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
                    nsc += f1 if r_ >= s else f0
                    if j == 0:
                        o = f1 if r_ < s else f0
                        sy = o * yv
                        st = o * tj
                        st2 = o * tj2
                        sav = o * aj
                        nv = o
                    else:
                        ys = s - d
                        o, c = _usable(r_, yv, ys, s, tj, tj2, aj, g32, sy, st, sav)
                        cb = c & (ys != f0)
                        cm |= (1 << j) if cb else 0
                        sy += o * yv
                        st += o * tj
                        st2 += o * tj2
                        sav += o * aj
                        nv += o
                        nc += f1 if cb else f0
                    okm |= (1 << j) if o != f0 else 0
                # -- the pooled (Poisson) estimate, or the shortest exposure's lower bound
                has = nv > f0
                xi = sy / (st if has else f1)
                nsa = f0
                if not has:
                    nsa = nsc
                    xi = (np.float32(zs[0][l, a, i]) - darks[0, a, i]) / times[0]
                xp = max(xi, f0)
                # -- the method's weighted estimate (the stage kernel's per-exposure passes)
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
                        # g(y) = ln y of the fractional y = raw − dark: the rounded level
                        # was off by up to ½ DN per (column, band) dark, a bias of up to
                        # ½/y (1.7 % at 30 DN, 0.3 % at 160). (max: y > floor ≥ ½ wherever
                        # w > 0, it only keeps ln finite where w = 0. ln t_j as the stage
                        # kernel takes it; LLVM hoists it. No scratch array: the kernel
                        # allocates nothing, see mehs.synthesis._native)
                        num += w * (logf(max(yj, half)) - np.float32(np.log(tj)))
                    else:
                        num += w * yj / tj
                    den += w
                    if deb:
                        # the SNR's sums (see below), while w is at hand
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
                # -- noise-model SNR: Σω and Σω²·var with var from the (clipped) estimate
                x = xm if (xm >= f0) & (xm < inf32) else f0
                if deb:
                    # Σω²·var = g·x·Σω²/t + Σ(ω/t)²·a + rel·x²·Σω² from the sums taken with
                    # the weights (recomputing Debevec's weights here cost 20 % of the
                    # kernel); for the pooled weights ω = t they are exactly the selection's
                    # Σt, Σa, Σt² (t/t = 1). The stage kernel's SNR pass takes the same form.
                    snum = st if pooled_w else den
                    sden = (g32 * x * (st if pooled_w else s1) + (sav if pooled_w else s2)
                            + rel32 * x * x * (st2 if pooled_w else s3))
                else:
                    # Robertson's and inverse variance's weights LLVM shares with the
                    # loop above (the sums' divisions made them 5-20 % slower)
                    snum = f0
                    sden = f0
                    for j in range(P):
                        tj = times[j]
                        aj = avar[j]
                        okj = f1 if (okm >> j) & 1 else f0
                        yj = np.float32(zs[j][l, a, i]) - darks[j, a, i]
                        w = (okj * tj if pooled_w
                             else _method_weight(method, okj, yj, xp, tj, aj, g32, top, hmid, fl))
                        v = (g32 * x * tj + aj) / (tj * tj) + rel32 * x * x
                        snum += okj * w
                        sden += okj * w * w * v
                # -- the consistency statistic about the pooled estimate (as Poisson)
                qc = f0
                if want_chi2:
                    qc = _consistency(zs, l, a, i, darks, s, times, avar, g32, rel32, xp, okm, cm)
                # -- write (the stage kernel's _write_row)
                fin = (xm > -inf32) & (xm < inf32)
                xo = xm if fin & (xm >= f0) else f0
                xr = xm if fin else f0
                ol[i] = (xo if clip else xr) * c_a
                msum_l[i] += xo * c_a
                nvalid_l[i] += 1 if has else 0
                snr_l[i] += xo * snum / np.sqrt(sden) if has & (sden > f0) else f0
                nsat_l[i] += 1 if nsa == fP else 0
                if want_chi2:
                    ne = nv + nc
                    m2 = (ne >= two) & (nv > f0)
                    chi2_l[i] += qc if m2 else f0
                    dof_l[i] += np.int32(ne) - np.int32(1) if m2 else np.int32(0)


@njit(nogil=True, cache=True, error_model="numpy")
def merge_chunk_debevec_linear(zs, darks, sat, times, L, floor, gain, avar, rel_var, cal,
                               want_chi2, clip, out, chi2, dof, snr, nsat, nvalid, msum):
    """Debevec & Malik's log-domain mean of a linear sensor (see :func:`_merge_weighted`)."""
    _merge_weighted(zs, darks, sat, times, L, floor, gain, avar, rel_var, cal, DEBEVEC,
                    want_chi2, clip, out, chi2, dof, snr, nsat, nvalid, msum)


@njit(nogil=True, cache=True, error_model="numpy")
def merge_chunk_robertson_linear(zs, darks, sat, times, L, floor, gain, avar, rel_var, cal,
                                 want_chi2, clip, out, chi2, dof, snr, nsat, nvalid, msum):
    """Robertson et al.'s ``w·t²``-weighted mean of a linear sensor (see :func:`_merge_weighted`)."""
    _merge_weighted(zs, darks, sat, times, L, floor, gain, avar, rel_var, cal, ROBERTSON,
                    want_chi2, clip, out, chi2, dof, snr, nsat, nvalid, msum)


@njit(nogil=True, cache=True, error_model="numpy")
def merge_chunk_invvar_linear(zs, darks, sat, times, L, floor, gain, avar, rel_var, cal,
                              want_chi2, clip, out, chi2, dof, snr, nsat, nvalid, msum):
    """Inverse-variance weights of a linear sensor (see :func:`_merge_weighted`)."""
    _merge_weighted(zs, darks, sat, times, L, floor, gain, avar, rel_var, cal, INVVAR,
                    want_chi2, clip, out, chi2, dof, snr, nsat, nvalid, msum)


# The radiance-only kernels: the statistic off as a compile-time constant, whatever
# ``want_chi2`` says (see merge_chunk_poisson_linear_radiance for why: spills in the
# vectorised loop with a run-time flag; one kernel with both loops would double a
# first-ever compile).
@njit(nogil=True, cache=True, error_model="numpy")
def merge_chunk_debevec_linear_radiance(zs, darks, sat, times, L, floor, gain, avar, rel_var,
                                        cal, want_chi2, clip, out, chi2, dof, snr, nsat,
                                        nvalid, msum):
    """:func:`merge_chunk_debevec_linear` without the χ² statistic."""
    _merge_weighted(zs, darks, sat, times, L, floor, gain, avar, rel_var, cal, DEBEVEC,
                    False, clip, out, chi2, dof, snr, nsat, nvalid, msum)


@njit(nogil=True, cache=True, error_model="numpy")
def merge_chunk_robertson_linear_radiance(zs, darks, sat, times, L, floor, gain, avar,
                                          rel_var, cal, want_chi2, clip, out, chi2, dof, snr,
                                          nsat, nvalid, msum):
    """:func:`merge_chunk_robertson_linear` without the χ² statistic."""
    _merge_weighted(zs, darks, sat, times, L, floor, gain, avar, rel_var, cal, ROBERTSON,
                    False, clip, out, chi2, dof, snr, nsat, nvalid, msum)


@njit(nogil=True, cache=True, error_model="numpy")
def merge_chunk_invvar_linear_radiance(zs, darks, sat, times, L, floor, gain, avar, rel_var,
                                       cal, want_chi2, clip, out, chi2, dof, snr, nsat,
                                       nvalid, msum):
    """:func:`merge_chunk_invvar_linear` without the χ² statistic."""
    _merge_weighted(zs, darks, sat, times, L, floor, gain, avar, rel_var, cal, INVVAR,
                    False, clip, out, chi2, dof, snr, nsat, nvalid, msum)
