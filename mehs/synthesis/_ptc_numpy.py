"""The photon-transfer pass and subset of :mod:`mehs.synthesis._ptc_kernels` as
whole-array numpy, and the cells of a subset of samples.

:func:`ptc_pass` and :func:`ptc_subset` take the compiled kernels' arguments and give
their outputs to the bit: the cells and flags are integer work, the subset's ``d`` and
own level the same float64 expressions, and ``np.bincount`` adds its float64 weights in
sample order, as the compiled loop does. They run while the compiled kernels are still
being compiled in child processes (a first-ever ``mehs fuse``): ~20 numpy passes over a
pair's samples take ~0.05 s, where waiting for those children took 3–5 s on two cores
shared with the merge kernel's own compilation (issue 16). No numba here.
"""

from __future__ import annotations

import numpy as np


def cell_keys(inst: np.ndarray, cell_bits: int) -> np.ndarray:
    """int32 cells of float32 values (:func:`mehs.synthesis._ptc_kernels._row_cells`)."""
    bits = np.asarray(inst, dtype=np.float32).view(np.int32)
    m = bits >> 31
    return ((((bits & np.int32(0x7FFFFFFF)) ^ m) - m) >> np.int32(32 - cell_bits)) \
        + np.int32(1 << (cell_bits - 1))


def cells_flags(y_j, y_k, raw_j, raw_k, sat, nbr, cell_bits, index=None):
    """int32 each sample's cell and bool its saturation flag: (n, bands) arrays, or for
    the pixel-major flat sample indices ``index`` only."""
    if index is None:
        inst = np.take(np.asarray(y_j + y_k, dtype=np.float32), nbr, axis=1)
        sat_k = raw_k >= sat
        return (cell_keys(inst, cell_bits),
                sat_k | np.take(sat_k, nbr, axis=1) | (raw_j >= sat))
    b = index % y_j.shape[1]
    c = nbr[b]
    at_c = index + (c - b)                          # the instrument's sample, flat
    yj, yk, rj, rk = (a.reshape(-1) for a in (y_j, y_k, raw_j, raw_k))
    inst = np.asarray(yj[at_c] + yk[at_c], dtype=np.float32)
    s_b = sat[b]
    return (cell_keys(inst, cell_bits),
            (rk[index] >= s_b) | (rk[at_c] >= sat[c]) | (rj[index] >= s_b))


def ptc_subset(y_j, y_k, raw_j, raw_k, sat, nbr, cell_bits, step, r, cells, ds, qs, pix,
               count):
    """:func:`mehs.synthesis._ptc_kernels.ptc_subset`."""
    n, nb = y_j.shape
    index = np.arange(0, n * nb, step)
    c, bad = cells_flags(y_j, y_k, raw_j, raw_k, sat, nbr, cell_bits, index)
    at = index[~bad]
    k = at.size
    cells[:k] = c[~bad]
    yj = y_j.reshape(-1)[at].astype(np.float64)
    yk = y_k.reshape(-1)[at].astype(np.float64)
    ds[:k] = yk - np.float64(r) * yj
    qs[:k] = np.float64(r) * (yk + yj)
    pix[:k] = at // nb
    count[0] = k


def ptc_pass(y_j, y_k, raw_j, raw_k, sat, nbr, cell_bits, key_row, cp, sat_row, bp,
             r, lo, table, med, lim, nall, nbad, nt, se, se2, syj):
    """:func:`mehs.synthesis._ptc_kernels.ptc_pass` (the row scratch unused)."""
    c, b = cells_flags(y_j, y_k, raw_j, raw_k, sat, nbr, cell_bits)
    g = np.take(table, np.clip(c.ravel().astype(np.int64) - lo, 0, table.size - 1))
    g = g.astype(np.intp)
    b = b.ravel()
    G = nt.size
    nall += np.bincount(g, minlength=G)
    nbad += np.bincount(g[b], minlength=G)
    yj = y_j.ravel().astype(np.float64)
    e = (y_k.ravel().astype(np.float64) - r * yj) - np.take(med, g)
    t = ~b & (np.abs(e) <= np.take(lim, g))
    gt, et = g[t], e[t]
    nt += np.bincount(gt, minlength=G)
    se += np.bincount(gt, weights=et, minlength=G)
    se2 += np.bincount(gt, weights=et * et, minlength=G)
    syj += np.bincount(gt, weights=yj[t], minlength=G)
