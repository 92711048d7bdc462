"""Tile geometry and seam blending of tiled inference (:mod:`mehs.ssr.tiling`).

The bottom of the tiling code: where tiles sit on an image (origins on the
network's pooling grid, a fixed overlap), the weight ramps that cross-fade
neighbours, and :func:`predict_tiled`, which runs a per-tile function and
stitches its outputs. The planner (how large a tile may be) and the network
hooks live in :mod:`mehs.ssr.tiling`, which re-exports these names.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np

from mehs.errors import InputError


@dataclass(frozen=True)
class TilingPlan:
    """Tile size and overlap for one image; ``tile = None`` means "run the image whole".

    ``tile`` (height) and ``tile_w`` (width; default ``tile``) and every tile
    origin are multiples of ``align``; ``margin`` pixels at each edge shared
    with a neighbour get zero weight, then a ``blend``-pixel linear ramp.
    """

    tile: int | None
    margin: int
    blend: int
    align: int
    tile_w: int | None = None

    @property
    def overlap(self) -> int:
        return 2 * self.margin + self.blend

    @property
    def width(self) -> int | None:
        return self.tile_w if self.tile_w is not None else self.tile


def _covered(n: int, tile: int, overlap: int, align: int) -> int:
    """Pixels computed along one axis: the summed lengths of its tiles."""
    starts = tile_starts(n, tile, overlap, align)
    return sum(min(tile, n - s) for s in starts[:-1]) + (n - starts[-1])


def tile_starts(n: int, tile: int, overlap: int, align: int) -> list[int]:
    """Origins along one axis of length ``n``: multiples of ``align``, a step of ``tile − overlap``.

    The last tile runs from its origin to the end of the axis (at most ``tile``
    long, and longer than ``overlap``), so every origin stays on the grid.
    """
    if tile >= n:
        return [0]
    step = (tile - overlap) // align * align
    if step <= 0:
        raise InputError(f"tile {tile} leaves no core after an overlap of {overlap}")
    starts = [0]
    while starts[-1] + tile < n:
        starts.append(starts[-1] + step)
    return starts


def owned_cells(n: int, m: int, lo: int, hi: int, last: bool, what: str = "",
                cell: int | None = None) -> tuple[int, int]:
    """The cells ``[lo // s, hi // s)`` of an ``m``-cell pooled map of an ``n``-pixel tile
    axis that the tile owns (owned pixels ``[lo, hi)``; to the map's end when ``last``).

    The map covers the tile padded up to the pooling grid (only the image's last tile
    is padded): each cell is ``s = ceil(n / m)`` pixels, or ``cell`` where given: a
    network that pads inside to its own grid pools an image's last tile over that
    padding, whose cells ``ceil`` misjudges (a 108-pixel tile padded to 128 pools to 16
    cells of 8, not 7); they are the cells of the tiles before it, which need none.
    The owned span must fall on cell boundaries.
    """
    s = cell or -(-n // m)
    if m * s < n or (not last and m * s != n) or lo % s or (not last and hi % s):
        raise InputError(f"{what + ': ' if what else ''}a {n}-pixel tile gave a {m}-cell "
                         f"pooled map whose cells do not fall on the owned span [{lo}, {hi}): "
                         "image-wide means need the tiles on the network's pooling grid "
                         "(model.tiling['align'])")
    return lo // s, (m if last else hi // s)


def _ramp(length: int, lo_inner: bool, hi_inner: bool, margin: int, blend: int) -> np.ndarray:
    """float32 ``(length,)``: 0 in the margin at an inner edge, then a ``blend`` ramp to 1."""
    w = np.ones(length, dtype=np.float32)
    ramp = np.clip((np.arange(length, dtype=np.float32) - margin + 1) / (blend + 1), 0, 1)
    if lo_inner:
        w = np.minimum(w, ramp)
    if hi_inner:
        w = np.minimum(w, ramp[::-1])
    return w


def _axis_pieces(n: int, tile: int, plan: TilingPlan) -> list[tuple[int, int, list]]:
    """Per tile along one axis: its span ``(start, end)`` and the pieces where it has weight.

    Each piece is ``(a, b, weights)``: image positions ``[a, b)`` and the tile's
    float32 weights there, normalised so that all tiles' weights sum to 1 at
    every position; ``weights`` is None where the tile alone has weight (1).
    """
    starts = tile_starts(n, tile, plan.overlap, plan.align)
    spans, ramps = [], []
    total = np.zeros(n, dtype=np.float32)
    for i, s in enumerate(starts):
        e = n if i == len(starts) - 1 else s + tile
        r = _ramp(e - s, i > 0, i < len(starts) - 1, plan.margin, plan.blend)
        total[s:e] += r
        spans.append((s, e))
        ramps.append(r)
    out = []
    for (s, e), r in zip(spans, ramps):
        nz = np.flatnonzero(r)           # never empty: tile_starts keeps a core
        lo, hi = s + int(nz[0]), s + int(nz[-1]) + 1
        wn = r[lo - s:hi - s] / total[lo:hi]
        sole = wn == 1
        pieces, a = [], lo
        while a < hi:                                  # runs of sole (1) and shared weights
            b = a + 1
            while b < hi and sole[b - lo] == sole[a - lo]:
                b += 1
            pieces.append((a, b, None if sole[a - lo] else wn[a - lo:b - lo]))
            a = b
        out.append((s, e, pieces))
    return out


def _small_page_zeros(shape: tuple[int, ...]) -> np.ndarray:
    """float32 zeros in an anonymous mapping that declines transparent huge pages.

    numpy advises huge pages for large arrays; where the kernel compacts memory
    on such a fault (``defrag = madvise``, the common default) and a network run
    has just fragmented it, the stitched output and the arrays after it stalled
    for seconds (2048×1024 tiles: stitching 0.65 s and luminance restoration 2.7 s
    of system time, against 0.2 s and 0.3 s without huge pages; issue 16).
    """
    import mmap

    n = int(np.prod(shape)) * 4
    if n == 0 or not hasattr(mmap, "MADV_NOHUGEPAGE"):
        return np.zeros(shape, dtype=np.float32)
    buf = mmap.mmap(-1, n)                    # anonymous: zero pages, touched lazily
    buf.madvise(mmap.MADV_NOHUGEPAGE)
    return np.frombuffer(buf, dtype=np.float32).reshape(shape)


def predict_tiled(fn: Callable[[np.ndarray], np.ndarray], rgb: np.ndarray, plan: TilingPlan,
                  *, on_tile: Callable[[int, int, int, int], None] | None = None) -> np.ndarray:
    """Run ``fn`` on overlapping tiles of ``rgb`` and blend the results.

    Parameters
    ----------
    fn
        ``(h, w, 3) → (h, w, B)`` float32, e.g. a network's whole-image call.
    rgb
        float32 ``(H, W, 3)``.
    plan
        From :func:`plan_tiles`; ``plan.tile is None`` runs the image whole.
    on_tile
        Called as ``on_tile(y0, y1, x0, x1)`` before ``fn`` runs on rows ``[y0, y1)``
        and columns ``[x0, x1)`` (image-wide statistics, :mod:`mehs.ssr.tiling_global`).

    Returns
    -------
    float32 ``(H, W, B)``: ``Σ w_k y_k / Σ w_k`` over the tiles covering each pixel.
    Where one tile alone has weight its output is copied; the weights are
    per-axis ramps normalised once, so no full-size weight map is kept, and
    the output is laid out like the tiles' outputs (band-major for torch).
    """
    if plan.tile is None:
        return np.asarray(fn(rgb), dtype=np.float32)
    h, w = rgb.shape[:2]
    rows, cols = _axis_pieces(h, plan.tile, plan), _axis_pieces(w, plan.width, plan)
    out = None
    for y0, y1, row_pieces in rows:
        for x0, x1, col_pieces in cols:
            # no malloc_trim between tiles: the next tile of the same shape reuses the
            # freed heap blocks; trimming made it fault them in again (1.84× vs 1.33×
            # whole-image time on 2048×1024, peak 1.79 vs 1.88 GB)
            if on_tile is not None:
                on_tile(y0, y1, x0, x1)
            y = np.asarray(fn(np.ascontiguousarray(rgb[y0:y1, x0:x1])), dtype=np.float32)
            if y.ndim != 3 or y.shape[:2] != (y1 - y0, x1 - x0):
                raise InputError(f"the model turned a {y1 - y0}×{x1 - x0} tile into shape "
                                 f"{y.shape}; tiled inference needs (h, w, bands) out")
            if out is None:                   # zeros: pages are only touched as tiles land
                if y.transpose(2, 0, 1).flags.c_contiguous:
                    out = _small_page_zeros((y.shape[2], h, w)).transpose(1, 2, 0)
                else:
                    out = _small_page_zeros((h, w, y.shape[2]))
            src = None
            for a, b, wy in row_pieces:
                for c, d, wx in col_pieces:
                    src = y[a - y0:b - y0, c - x0:d - x0]
                    if wy is None and wx is None:
                        out[a:b, c:d] = src
                    else:
                        wt = (np.ones(b - a, np.float32) if wy is None else wy)[:, None] * \
                             (np.ones(d - c, np.float32) if wx is None else wx)[None, :]
                        out[a:b, c:d] += src * wt[:, :, None]
            del y, src                        # free this tile's output before the next runs
    return out
