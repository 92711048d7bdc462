"""The default merge (Poisson, linear sensor) with the χ² ghost statistic of *binned* bands.

The consistency statistic of :mod:`mehs.synthesis._merge_fused` is a χ² per pixel and
band, summed over the bands. Here it is taken on the sums of ``nbin`` adjacent bands:
per bin and exposure, the dark-subtracted levels summed over the bin's bands, their
variance the bin's (``g·x̂·t + nbin·a``, from the bin's pooled estimate ``x̂``, the sum of
its bands' estimates), one degree of freedom per used exposure and bin instead of per
band. A change that keeps its sign across a bin's neighbouring bands — a moving object's
spectrum against the one it covers, at a few nm per band — keeps its whole
non-centrality in ``1/nbin`` of the degrees of freedom, so the test at the same
false-alarm rate flags more of the weakly moving pixels (``benchmarks/bench_ghost_bands.py``:
bins of 4 flag 99.8 % of the pixels changed by 10–30σ over all bands, the per-band
statistic 93.5 %); a change whose sign flips within a bin partly cancels there. And it
costs ``1/nbin`` of the statistic's divisions.

Which exposures a bin uses follows the merge's own per-band choice: an exposure is used
in a bin where it is used in every band of it; it is *censored* in a bin where every band
either uses it or found it censored (saturated although the others predicted it well
below saturation) and one did — its lower bound is then the used bands' levels plus the
censored bands' saturation levels, and it adds ``w·(bound/t − x̄)²`` when above the mean,
as the per-band statistic does. With ``nbin = 1`` every number equals
:func:`mehs.synthesis._merge_fused.merge_chunk_poisson_linear`'s to the bit (tested).

The structure is what lets LLVM vectorise it: each band's sample loop is the radiance
loop of the one-pass kernel plus a few scratch updates (the bin's running sums in ``P``
*separate* rows ``ysum``, and ``xps``, ``bms``); the bin's statistic is a second loop over
the samples that reads only the scratch. LLVM gives up a loop needing more than 128
run-time alias checks, which grow with stores × load arrays: a bin's bands unrolled in one
loop, or the sums in the rows of one ``(P, samples)`` array, exceed it. The scratch comes
in as arguments (the stored C-callable kernels cannot allocate).
"""

from __future__ import annotations

import numpy as np
from numba import njit

from mehs.synthesis._merge_rows import _usable


@njit(cache=True, inline="always", error_model="numpy")
def _bin_statistic(ysum, xps, bms, times, avar, g32, rel32, kk, chi2_l, dof_l):
    """Add one bin's χ² and degrees of freedom to a line's ``chi2_l``, ``dof_l``, from the
    scratch its bands' sample loops left: ``ysum`` (the bin's summed levels per
    exposure), ``xps`` (its pooled estimate), ``bms`` (its exposure masks: used in every
    band, low 16 bits; used or censored in every band, high 16 bits); ``kk`` its number
    of bands (float32). Its own loop over the samples, inlined by numba into
    :func:`merge_chunk_poisson_linear_binned` and
    :mod:`mehs.synthesis._merge_binned_weighted`'s kernels."""
    P = len(ysum)
    ns = xps.shape[0]
    f0 = np.float32(0.0)
    f1 = np.float32(1.0)
    two = np.float32(2.0)
    for i in range(ns):
        xp = xps[i]
        m = bms[i]
        um = m & 0xFFFF
        cmb = (m >> 16) & ~um
        sw = f0
        swx = f0
        swx2 = f0
        nvb = f0
        ncb = f0
        for j in range(P):
            tj = times[j]
            itj = f1 / tj
            itj2 = itj * itj
            w = f1 / ((g32 * xp * tj + kk * avar[j]) * itj2 + rel32 * xp * xp)
            okj = f1 if (um >> j) & 1 else f0
            wx = okj * w * (ysum[j][i] * itj)
            if j == 0:
                sw = okj * w
                swx = wx
                swx2 = wx * (ysum[j][i] * itj)
            else:
                sw += okj * w
                swx += wx
                swx2 += wx * (ysum[j][i] * itj)
            nvb += okj
            ncb += f1 if (cmb >> j) & 1 else f0
        mean = swx / sw if sw > f0 else f0
        v = swx2 - swx * mean
        q = v if v > f0 else f0
        for j in range(1, P):
            tj = times[j]
            itj = f1 / tj
            itj2 = itj * itj
            w = f1 / ((g32 * xp * tj + kk * avar[j]) * itj2 + rel32 * xp * xp)
            r = ysum[j][i] * itj - mean
            cj = f1 if (cmb >> j) & 1 else f0
            q += cj * (w * r * r if r > f0 else f0)
        ne = nvb + ncb
        m2 = (ne >= two) & (nvb > f0)
        # products, not `q if m2 else 0`: with the branch LLVM sank the statistic
        # into it and gathered times[j] and avar[j] under masks
        chi2_l[i] += q * (f1 if m2 else f0)
        dof_l[i] += (np.int32(ne) - np.int32(1)) * (np.int32(1) if m2 else np.int32(0))


@njit(nogil=True, cache=True, error_model="numpy")
def merge_chunk_poisson_linear_binned(zs, darks, sat, times, gain, avar, rel_var, cal,
                                      want_chi2, clip, nbin, ysum, xps, bms, out, chi2, dof,
                                      snr, nsat, nvalid, msum):
    """Poisson merge ``X = Σy / Σt`` of a chunk of lines (BIL) from a linear sensor, with
    the χ² consistency statistic of bins of ``nbin`` adjacent bands (the last bin may be
    shorter).

    Arguments as :func:`mehs.synthesis._merge_fused.merge_chunk_poisson_linear`, plus
    ``nbin`` (≥ 1) and the scratch: ``ysum`` a tuple of ``P`` float32 rows of ``samples``
    values, ``xps`` float32 and ``bms`` int32 rows of ``samples`` values. ``want_chi2`` is
    ignored (this kernel is the statistic's). At most 16 exposures: ``bms`` holds two of
    their bit masks (the caller checks).
    """
    P = len(zs)
    nl, nb, ns = out.shape
    f0 = np.float32(0.0)
    f1 = np.float32(1.0)
    g32 = np.float32(gain)
    rel32 = np.float32(rel_var)
    inf32 = np.float32(np.inf)
    fP = np.float32(P)
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
                    # -- choose the samples: merge_chunk_poisson_linear's expressions, repeated
                    #    in place as _merge_fused_weighted repeats them (LLVM vectorises the
                    #    loop only with a sample's state in locals: an inline helper returning
                    #    it stopped that, see _merge_rows._usable)
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
                        # the bin's level: a used band's own, a censored one's saturation
                        # level (its lower bound; other bands leave the exposure out)
                        ysum[j][i] = (f0 if first else ysum[j][i]) + (yv if o != f0 else ys)
                    # -- pool, and Σω²var for the SNR (ω = t)
                    has = nv > f0
                    xi = sy / (st if has else f1)
                    x = xi if xi >= f0 else f0
                    den = g32 * x * st + sav + rel32 * x * x * st2
                    nsa = f0
                    if not has:
                        nsa = nsc
                        xi = (np.float32(zs[0][l, a, i]) - darks[0, a, i]) / times[0]
                    # -- write
                    fin = (xi > -inf32) & (xi < inf32)
                    xo = xi if fin & (xi >= f0) else f0
                    xr = xi if fin else f0
                    ol[i] = (xo if clip else xr) * c_a
                    msum_l[i] += xo * c_a
                    nvalid_l[i] += 1 if has else 0
                    snr_l[i] += xo * st / np.sqrt(den) if has & (den > f0) else f0
                    nsat_l[i] += 1 if nsa == fP else 0
                    # -- the bin's running estimate and exposure masks: used in every band
                    #    (low 16 bits), used or censored in every band (high 16 bits)
                    xps[i] = (f0 if first else xps[i]) + max(xi, f0)
                    m = okm | ((okm | cm) << 16)
                    bms[i] = m if first else (bms[i] & m)
            # -- the bin's statistic, from the scratch alone
            _bin_statistic(ysum, xps, bms, times, avar, g32, rel32, np.float32(kb), chi2_l, dof_l)
