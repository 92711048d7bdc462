"""The per-sample pass of the photon-transfer statistics, compiled (issue 16).

:func:`mehs.synthesis._ptc_groups.group_statistics` measures, for two exposures of the
probed lines, the mean and variance of ``d = y_k − r·y_j`` per signal level: the noise
model and the linearity test of every ``mehs fuse`` rest on it. As whole-array numpy
steps it took ~30 full passes over a pair's samples (0.15 s for a 512² scene, more than
the merge). The groups (cells of the instrument's value → group) and each group's
median and MAD come from an even subset of the samples (numpy, in ``_ptc_groups``), which
:func:`ptc_subset` gathers; what needs every sample is one loop, :func:`ptc_pass`: each
sample's group, its saturation, and the clipped sums ``n``, ``Σe``, ``Σe²``, ``Σy_j`` per
group.

The arithmetic and the order of every sum are numpy's (``bincount`` adds its float64
weights in sample order), so the statistics are the same to the bit as the numpy
formulation (:mod:`mehs.synthesis._ptc_numpy`, and the reference in the tests).
"""

from __future__ import annotations

import numpy as np
from numba import njit

from mehs.synthesis._cephes import f32_bits


@njit(cache=True, inline="always", error_model="numpy")
def _cell(v, shift, half):
    """The int32 cell of the float32 ``v``: the top bits of a key that sorts like the
    values (``−0.0`` and ``+0.0`` alike), ``shift = 32 − cell_bits``,
    ``half = 2**(cell_bits − 1)`` (see :func:`_row_cells`)."""
    bits = f32_bits(v)
    m = bits >> 31                               # −1 for a negative value, else 0
    return np.int32(((((bits & 0x7FFFFFFF) ^ m) - m) >> shift) + half)


@njit(cache=True, inline="always", error_model="numpy")
def _row_cells(yj, yk, rj, rk, sat, nbr, cell_bits, key_row, sat_row, cp, bp):
    """One pixel's row of samples: each band's cell ``cp`` (int32) and saturation flag
    ``bp`` (uint8). ``key_row``, ``sat_row``: scratch of the row's length.

    A sample's cell is the top ``cell_bits`` bits of a key of its instrument's (the
    neighbouring band's ``y_j + y_k``) float32 value that sorts like the values
    (``−0.0`` and ``+0.0`` alike): cells are 0.1–0.2 % of the value wide
    (``2**(cell_bits − 9)`` a binade), and every value of a cell lies below every value
    of a later one. It is saturated in either exposure or in the instrument's longer one.
    """
    nb = yj.shape[0]
    shift = 32 - cell_bits
    half = 1 << (cell_bits - 1)
    # the row's own keys first (a loop LLVM vectorises), then each band takes its
    # neighbour's
    for b in range(nb):
        key_row[b] = _cell(np.float32(yj[b] + yk[b]), shift, half)
        sat_row[b] = 1 if rk[b] >= sat[b] else 0
    for b in range(nb):
        c = nbr[b]
        cp[b] = key_row[c]
        bp[b] = sat_row[b] | sat_row[c] | (1 if rj[b] >= sat[b] else 0)


@njit(nogil=True, cache=True, error_model="numpy")
def ptc_pass(y_j, y_k, raw_j, raw_k, sat, nbr, cell_bits, key_row, cp, sat_row, bp,
             r, lo, table, med, lim, nall, nbad, nt, se, se2, syj):
    """Per group: the count of all samples ``nall`` and of saturated ones ``nbad``, and of
    the unsaturated samples within ``lim`` of the group's median ``med`` their count
    ``nt``, ``Σe`` ``se``, ``Σe²`` ``se2`` (``e = d − med``, ``d = y_k − r·y_j`` in
    float64) and ``Σy_j`` ``syj``; all float64 (groups,), added to in sample order.

    ``y_j``, ``y_k`` (n, bands) linearised samples (float32, or float64 from a recovered
    curve: the instrument is grouped by its float32 value); ``raw_j``, ``raw_k`` (n, bands)
    float32 raw DN; ``sat`` (bands,) raw saturation; ``nbr`` (bands,) int64 the instrument
    band of each band; ``key_row``, ``cp`` int32 and ``sat_row``, ``bp`` uint8 (bands,):
    scratch (the kernel allocates nothing, so that its stored machine code needs none of
    numba's runtime). ``table`` (uint16) the group of each cell from ``lo`` on: a cell
    below the table belongs to its first entry's group, one above to its last's (the
    table spans the cells of a subset of the samples).
    """
    n, nb = y_j.shape
    last = table.shape[0] - 1
    for p in range(n):
        yj, yk = y_j[p], y_k[p]
        _row_cells(yj, yk, raw_j[p], raw_k[p], sat, nbr, cell_bits, key_row, sat_row, cp, bp)
        for b in range(nb):
            c = min(max(np.int64(cp[b]) - lo, 0), last)
            g = np.int64(table[c])
            nall[g] += 1.0
            if bp[b] != 0:
                nbad[g] += 1.0
                continue
            yjb = np.float64(yj[b])
            e = (np.float64(yk[b]) - r * yjb) - med[g]
            if abs(e) <= lim[g]:
                nt[g] += 1.0
                se[g] += e
                se2[g] += e * e
                syj[g] += yjb


@njit(nogil=True, cache=True, error_model="numpy")
def ptc_subset(y_j, y_k, raw_j, raw_k, sat, nbr, cell_bits, step, r, cells, ds, qs, pix,
               count):
    """The even subset of the samples: those at the flat pixel-major positions ``0, step,
    2·step, …`` that no exposure saturated (the flags of :func:`_row_cells`), packed to
    the front of the outputs in that order: ``cells`` (int32) the cell of each one's
    instrument (:func:`_row_cells`), ``ds`` its ``y_k − r·y_j`` and ``qs`` its own level
    ``r·(y_k + y_j)`` (float64, as :func:`mehs.synthesis._ptc_groups._own_level`),
    ``pix`` (int64) its pixel; ``count[0]`` how many.

    Arguments as :func:`ptc_pass`; ``step`` ≥ 1, the outputs at least as long as the
    positions (``⌈n·bands / step⌉``). One loop instead of ~15 numpy gathers and masks
    over the subset, which held the GIL while the other exposure pair's statistics
    waited for it (issue 16).
    """
    n, nb = y_j.shape
    shift = 32 - cell_bits
    half = 1 << (cell_bits - 1)
    k = 0
    for at in range(0, n * nb, step):
        p = at // nb
        b = at - p * nb
        c = nbr[b]
        s_b = sat[b]
        if raw_k[p, b] >= s_b or raw_k[p, c] >= sat[c] or raw_j[p, b] >= s_b:
            continue
        cells[k] = _cell(np.float32(y_j[p, c] + y_k[p, c]), shift, half)
        yjb = np.float64(y_j[p, b])
        ykb = np.float64(y_k[p, b])
        ds[k] = ykb - r * yjb
        qs[k] = r * (ykb + yjb)
        pix[k] = p
        k += 1
    count[0] = k
