"""The per-sample passes of the photon-transfer statistics, compiled (issue 16).

:func:`mehs.synthesis.noise._pair_groups_compute` measures, for two exposures of the
probed lines, the mean and variance of ``d = y_k − r·y_j`` per signal level: the noise
model and the linearity test of every ``mehs fuse`` rest on it. As whole-array numpy
steps it took ~30 full passes over 1.7 million samples a pair (0.15 s for a 512²
scene, more than the merge). Here those passes are two loops:

- :func:`ptc_cells`: each sample's cell of the instrument (the neighbouring band's
  ``y_j + y_k``: a 0.1–0.2 % wide range of its value) and its saturation flag, with the
  per-cell counts of all and of saturated samples;
- :func:`ptc_sums`: after the groups (a cell → group table) and each group's median and
  MAD are known, the clipped sums ``n``, ``Σe``, ``Σe²``, ``Σy_j`` per group.

(The medians stay numpy's: a compiled selection saved 1–2 ms and cost 0.6 s of
compilation on a first-ever run.)

The arithmetic and the order of every sum are numpy's (``bincount`` adds its float64
weights in sample order), so the statistics are the same to the bit as the numpy
formulation they replace (tested against it).
"""

from __future__ import annotations

import numpy as np
from numba import njit

from mehs.synthesis._cephes import f32_bits


@njit(cache=True, inline="always", error_model="numpy")
def _row_cells(yj, yk, rj, rk, sat, nbr, cell_bits, key_row, sat_row, cp, bp):
    """One pixel's row of samples: each band's cell ``cp`` (int32) and saturation flag
    ``bp`` (uint8). ``key_row``, ``sat_row``: scratch of the row's length."""
    nb = yj.shape[0]
    shift = 32 - cell_bits
    half = 1 << (cell_bits - 1)
    # the row's own keys first (a loop LLVM vectorises), then each band takes its
    # neighbour's
    for b in range(nb):
        bits = f32_bits(np.float32(yj[b] + yk[b]))
        m = bits >> 31                           # −1 for a negative value, else 0
        key_row[b] = np.int32(((((bits & 0x7FFFFFFF) ^ m) - m) >> shift) + half)
        sat_row[b] = 1 if rk[b] >= sat[b] else 0
    for b in range(nb):
        c = nbr[b]
        cp[b] = key_row[c]
        bp[b] = sat_row[b] | sat_row[c] | (1 if rj[b] >= sat[b] else 0)


@njit(nogil=True, cache=True, inline="always", error_model="numpy")
def ptc_cells(y_j, y_k, raw_j, raw_k, sat, nbr, cell_bits, key_row, cp, sat_row, bp,
              count_all, count_bad, span, step, cells, bad):
    """Per-cell counts of all and of saturated samples of a pair, and the cells and flags
    of every ``step``-th sample.

    ``y_j``, ``y_k`` (n, bands) linearised samples (float32, or float64 from a recovered
    curve: the instrument is grouped by its float32 value); ``raw_j``, ``raw_k`` (n, bands)
    float32 raw DN; ``sat`` (bands,) raw saturation; ``nbr`` (bands,) int64 the instrument
    band of each band. A sample's cell is the top ``cell_bits`` bits of a key of its
    instrument's float32 value that sorts like the values (``−0.0`` and ``+0.0`` alike):
    cells are 0.1–0.2 % of the value wide (``2**(cell_bits − 9)`` a binade), and every
    value of a cell lies below every value of a later one. It is ``bad`` when saturated
    in either exposure or in the instrument's longer one. ``key_row``, ``cp`` int32 and
    ``sat_row``, ``bp`` uint8 (bands,): scratch (the kernels allocate nothing, so that
    their stored machine code needs none of numba's runtime).

    Adds to ``count_all`` and ``count_bad`` (2**cell_bits,), int32; writes ``span`` (2,)
    int32 the lowest and highest cell seen, and ``cells`` int32 / ``bad`` uint8
    (``ceil(n·bands/step)``,) of the samples ``0, step, 2·step, …`` in pixel-major order.
    """
    n, nb = y_j.shape
    lo = np.int32((1 << cell_bits) - 1)
    hi = np.int32(0)
    for p in range(n):
        _row_cells(y_j[p], y_k[p], raw_j[p], raw_k[p], sat, nbr, cell_bits, key_row,
                   sat_row, cp, bp)
        for b in range(nb):
            lo = min(lo, cp[b])
            hi = max(hi, cp[b])
        for b in range(nb):
            count_all[cp[b]] += 1
        for b in range(nb):
            if bp[b] != 0:
                count_bad[cp[b]] += 1
        f0 = p * nb
        f = (f0 + step - 1) // step * step
        while f < f0 + nb:
            cells[f // step] = cp[f - f0]
            bad[f // step] = bp[f - f0]
            f += step
    span[0] = lo
    span[1] = hi


@njit(nogil=True, cache=True, inline="always", error_model="numpy")
def ptc_sums(y_j, y_k, raw_j, raw_k, sat, nbr, cell_bits, key_row, cp, sat_row, bp,
             r, lo, table, med, lim, nt, se, se2, syj):
    """Per group, the samples within ``lim`` of the group's median ``med``: their count
    ``nt``, ``Σe`` ``se``, ``Σe²`` ``se2`` (``e = d − med``, ``d = y_k − r·y_j`` in
    float64) and ``Σy_j`` ``syj``, added in sample order.

    The first eleven arguments as :func:`ptc_cells` (each sample's cell is found again:
    cheaper than storing and reading them back); ``table`` the group of each cell from
    ``lo`` on; a group out of use has a negative ``lim``; saturated samples never count.
    (One scalar loop: staging each row's groups and residuals for a vectorised pass
    measured 20 % slower.)
    """
    n, nb = y_j.shape
    for p in range(n):
        yj, yk = y_j[p], y_k[p]
        _row_cells(yj, yk, raw_j[p], raw_k[p], sat, nbr, cell_bits, key_row, sat_row, cp, bp)
        for b in range(nb):
            g = np.int64(table[cp[b] - lo])
            yjb = np.float64(yj[b])
            e = (np.float64(yk[b]) - r * yjb) - med[g]
            if (bp[b] == 0) & (abs(e) <= lim[g]):
                nt[g] += 1.0
                se[g] += e
                se2[g] += e * e
                syj[g] += yjb


#: :func:`ptc_pass`'s operations
CELLS, SUMS = 0, 1


@njit(nogil=True, cache=True, error_model="numpy")
def ptc_pass(op, y_j, y_k, raw_j, raw_k, sat, nbr, cell_bits, key_row, cp, sat_row, bp,
             count_all, count_bad, span, step, cells, bad,
             r, lo, table, med, lim, nt, se, se2, syj):
    """:func:`ptc_cells` (``op`` :data:`CELLS`) or :func:`ptc_sums` (:data:`SUMS`) behind
    one entry point, both inlined: one numba compilation (2.0 s on a first-ever ``mehs
    fuse``, against 2.2 s for the two apart), the other operation's arguments unused."""
    if op == CELLS:
        ptc_cells(y_j, y_k, raw_j, raw_k, sat, nbr, cell_bits, key_row, cp, sat_row, bp,
                  count_all, count_bad, span, step, cells, bad)
    elif op == SUMS:
        ptc_sums(y_j, y_k, raw_j, raw_k, sat, nbr, cell_bits, key_row, cp, sat_row, bp,
                 r, lo, table, med, lim, nt, se, se2, syj)

