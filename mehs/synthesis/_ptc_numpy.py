"""The photon-transfer passes of :mod:`mehs.synthesis._ptc_kernels` as whole-array numpy.

Same arguments, same outputs, same bits: the cells and flags are integer work, and
``np.bincount`` adds its float64 weights in sample order, as the compiled loop does.
They run while the compiled passes are still being compiled in a child process (a
first-ever ``mehs fuse``): ~30 numpy passes over a pair's samples take ~0.1 s, where
waiting for that child took 3–5 s on two cores shared with the merge kernel's own
compilation (issue 16). No numba here.
"""

from __future__ import annotations

import numpy as np


def _cells_flags(y_j, y_k, raw_j, raw_k, sat, nbr, cell_bits):
    """int32 (n, bands) each sample's cell and bool (n, bands) its saturation flag
    (:func:`mehs.synthesis._ptc_kernels._row_cells`, every row at once)."""
    inst = np.asarray(y_j + y_k, dtype=np.float32)
    bits = inst.view(np.int32)
    m = bits >> 31
    key = ((((bits & np.int32(0x7FFFFFFF)) ^ m) - m) >> np.int32(32 - cell_bits)) \
        + np.int32(1 << (cell_bits - 1))
    sat_k = raw_k >= sat
    cp = np.take(key, nbr, axis=1)
    bp = sat_k | np.take(sat_k, nbr, axis=1) | (raw_j >= sat)
    return cp, bp


def ptc_cells(y_j, y_k, raw_j, raw_k, sat, nbr, cell_bits, key_row, cp, sat_row, bp,
              count_all, count_bad, span, step, cells, bad):
    """:func:`mehs.synthesis._ptc_kernels.ptc_cells` (the row scratch unused)."""
    c, b = _cells_flags(y_j, y_k, raw_j, raw_k, sat, nbr, cell_bits)
    c, b = c.ravel(), b.ravel()
    size = count_all.size
    count_all += np.bincount(c, minlength=size).astype(np.int32)
    count_bad += np.bincount(c[b], minlength=size).astype(np.int32)
    span[0] = min(int(c.min()), size - 1) if c.size else size - 1
    span[1] = max(int(c.max()), 0) if c.size else 0
    cells[:] = c[::step]
    bad[:] = b[::step]


def ptc_sums(y_j, y_k, raw_j, raw_k, sat, nbr, cell_bits, key_row, cp, sat_row, bp,
             r, lo, table, med, lim, nt, se, se2, syj):
    """:func:`mehs.synthesis._ptc_kernels.ptc_sums` (the row scratch unused)."""
    c, b = _cells_flags(y_j, y_k, raw_j, raw_k, sat, nbr, cell_bits)
    g = np.take(table, c.ravel() - lo).astype(np.intp)
    yj = y_j.ravel().astype(np.float64)
    e = (y_k.ravel().astype(np.float64) - r * yj) - np.take(med, g)
    t = ~b.ravel() & (np.abs(e) <= np.take(lim, g))
    gt, et = g[t], e[t]
    G = nt.size
    nt += np.bincount(gt, minlength=G)
    se += np.bincount(gt, weights=et, minlength=G)
    se2 += np.bincount(gt, weights=et * et, minlength=G)
    syj += np.bincount(gt, weights=yj[t], minlength=G)
