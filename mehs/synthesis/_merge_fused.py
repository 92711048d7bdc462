"""The default merge (Poisson, linear sensor) as one pass per sample (issue 16).

:func:`mehs.synthesis._merge_kernels.merge_chunk_poisson` works a row (one line,
one band) at a time in stages — choose the samples of each exposure, pool them,
the consistency sums of each exposure, write — each a vectorised loop over the
row that keeps its running sums in per-row scratch arrays: about 35 stores and
50 loads per pixel and band besides the arithmetic. Here the exposures are the
*inner* loop of each sample (``P`` is a compile-time constant of the tuple of
exposures, so LLVM unrolls it) and the samples the vectorised outer one: the
running sums, the choice of each exposure (a bit mask) and the consistency sums
stay in registers, and the stores are the outputs.

The arithmetic is the stage kernel's, expression for expression and in the same
order, so the results are the same to the bit (tested against it: censored,
saturated-in-all and negative samples, with and without the χ² statistic):
it replaces that kernel for the common case only, a linear response curve; the
non-linear one keeps the stage kernel.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from mehs.synthesis._merge_rows import _usable


@njit(cache=True, inline="always", error_model="numpy")
def _consistency(zs, l, a, i, darks, s, times, avar, g32, rel32, xp, okm, cm):
    """The stage kernel's consistency statistic of one sample (``_chi2_sums``,
    ``_chi2_censored``): ``Σw(x − x̄)²`` over the usable exposures (bit mask ``okm``)
    about their inverse-variance mean, ``w`` from the pooled estimate ``xp ≥ 0``, plus
    the censored residuals (bit mask ``cm``). One value out: numba inlines it and the
    sample loop still vectorises."""
    P = len(zs)
    f0 = np.float32(0.0)
    f1 = np.float32(1.0)
    sw = f0
    swx = f0
    swx2 = f0
    for j in range(P):
        tj = times[j]
        itj = f1 / tj
        itj2 = itj * itj
        w = f1 / ((g32 * xp * tj + avar[j]) * itj2 + rel32 * xp * xp)
        okj = f1 if (okm >> j) & 1 else f0
        yj = np.float32(zs[j][l, a, i]) - darks[j, a, i]
        wx = okj * w * (yj * itj)
        if j == 0:
            sw = okj * w
            swx = wx
            swx2 = wx * (yj * itj)
        else:
            sw += okj * w
            swx += wx
            swx2 += wx * (yj * itj)
    mean = swx / sw if sw > f0 else f0
    v = swx2 - swx * mean
    q = v if v > f0 else f0
    # a sample saturated where the others predicted it well below (the bits of cm). Not
    # under `if cm != 0` or `if (cm >> j) & 1`: LLVM if-converts that in the vectorised
    # loop anyway, and numba on Python >= 3.12 left reference counts of the arrays read
    # in such a block unpruned, whose calls kept the sample loop scalar (8-11x slower).
    # Adding 0.0 where the bit is clear leaves q's bits as they were.
    for j in range(1, P):
        tj = times[j]
        itj = f1 / tj
        itj2 = itj * itj
        w = f1 / ((g32 * xp * tj + avar[j]) * itj2 + rel32 * xp * xp)
        r = (s - darks[j, a, i]) * itj - mean
        q += w * r * r if ((cm >> j) & 1 != 0) & (r > f0) else f0
    return q


@njit(nogil=True, cache=True, error_model="numpy")
def merge_chunk_poisson_linear(zs, darks, sat, times, gain, avar, rel_var, cal, want_chi2,
                               clip, out, chi2, dof, snr, nsat, nvalid, msum):
    """Poisson merge ``X = Σy / Σt`` of a chunk of lines (BIL) from a linear sensor.

    Arguments as :func:`mehs.synthesis._merge_kernels.merge_chunk_poisson` (without the
    look-up tables of a non-linear curve). The merge calls it for the χ² ghost statistic;
    without the statistic it calls :func:`merge_chunk_poisson_linear_radiance`.
    """
    _poisson_linear(zs, darks, sat, times, gain, avar, rel_var, cal, want_chi2, clip,
                    out, chi2, dof, snr, nsat, nvalid, msum)


@njit(nogil=True, cache=True, error_model="numpy")
def merge_chunk_poisson_linear_radiance(zs, darks, sat, times, gain, avar, rel_var, cal,
                                        want_chi2, clip, out, chi2, dof, snr, nsat, nvalid,
                                        msum):
    """:func:`merge_chunk_poisson_linear` without the χ² statistic, whatever ``want_chi2``
    says (``chi2`` and ``dof`` are left as they are).

    Its own kernel, the statistic off as a compile-time constant: with a run-time flag
    LLVM kept the flag's test inside the vectorised sample loop, and the radiance-only
    merge carried the statistic's registers (about 45 spills and reloads per 16 samples;
    25 % slower). One kernel with both loops would double the first-ever compile of
    ``mehs fuse``, which needs only one.
    """
    _poisson_linear(zs, darks, sat, times, gain, avar, rel_var, cal, False, clip,
                    out, chi2, dof, snr, nsat, nvalid, msum)


@njit(cache=True, inline="always", error_model="numpy")
def _poisson_linear(zs, darks, sat, times, gain, avar, rel_var, cal, want_chi2, clip,
                    out, chi2, dof, snr, nsat, nvalid, msum):
    P = len(zs)
    nl, nb, ns = out.shape
    f0 = np.float32(0.0)
    f1 = np.float32(1.0)
    g32 = np.float32(gain)
    rel32 = np.float32(rel_var)
    inf32 = np.float32(np.inf)
    fP = np.float32(P)
    two = np.float32(2.0)
    for l in range(nl):
        ol_ = out[l]
        snr_l, msum_l, nvalid_l, nsat_l = snr[l], msum[l], nvalid[l], nsat[l]
        chi2_l, dof_l = chi2[l], dof[l]
        for a in range(nb):
            s = sat[a]
            c_a = cal[a]
            ol = ol_[a]
            for i in range(ns):
                # -- choose the samples (the stage kernel's _select_row, linear path)
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
                        # (a censored level of exactly 0 counts as none, as in the stage kernel)
                        cb = c & (ys != f0)
                        cm |= (1 << j) if cb else 0
                        sy += o * yv
                        st += o * tj
                        st2 += o * tj2
                        sav += o * aj
                        nv += o
                        nc += f1 if cb else f0
                    okm |= (1 << j) if o != f0 else 0
                # -- pool, and Σω²var for the SNR (ω = t)
                has = nv > f0
                xi = sy / (st if has else f1)
                x = xi if xi >= f0 else f0
                den = g32 * x * st + sav + rel32 * x * x * st2
                nsa = f0
                if not has:
                    # no usable sample: the shortest exposure's lower bound
                    nsa = nsc
                    xi = (np.float32(zs[0][l, a, i]) - darks[0, a, i]) / times[0]
                # -- the consistency statistic about the inverse-variance mean
                q = f0
                if want_chi2:
                    q = _consistency(zs, l, a, i, darks, s, times, avar, g32, rel32,
                                     max(xi, f0), okm, cm)
                # -- write (the stage kernel's _write_row)
                fin = (xi > -inf32) & (xi < inf32)
                xo = xi if fin & (xi >= f0) else f0
                xr = xi if fin else f0
                ol[i] = (xo if clip else xr) * c_a
                msum_l[i] += xo * c_a
                nvalid_l[i] += 1 if has else 0
                snr_l[i] += xo * st / np.sqrt(den) if has & (den > f0) else f0
                nsat_l[i] += 1 if nsa == fP else 0
                if want_chi2:
                    ne = nv + nc
                    m2 = (ne >= two) & (nv > f0)
                    chi2_l[i] += q if m2 else f0
                    dof_l[i] += np.int32(ne) - np.int32(1) if m2 else np.int32(0)
