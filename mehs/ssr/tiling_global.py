"""Tiled inference with image-wide global statistics: tiles that equal the whole image.

Run tile by tile with each tile's own channel-attention means, the paper's network is
not whole-image inference (interior differences up to ~1e-3 of the output's range
where the attention depends strongly on the image). So by default
(``model.tiling["statistics"]`` / ``MEHS_TILE_STATISTICS``: ``"auto"``) a torch
network whose only global operations are sums over pixels through
:func:`mehs.ssr.net.pooling.image_statistic` (average poolings, :func:`pooled_mean`;
MST++'s channel similarity) is tiled by :func:`predict_tiled_image_means`:

1. a collecting run over the tiles, each with its own means, sums every pooling
   layer's features over the part of the image each tile owns
   (:class:`mehs.ssr.net.pooling.ImageMeans`): image-wide means. It stops each
   forward at the last pooling, learnt from a forward on a small crop (the paper
   network's basis branches after it are 45 % of a forward);
2. the tiles run again with those means and collect again; the output of a run is
   returned once the means it was given and the means it measured agree to
   ``tol`` (relative to each layer's largest mean), else one more run.

The owned parts of an axis are split at a multiple of the pooling grid inside each
overlap, at least ``margin`` from either tile's edge, where a tile's features are the
whole image's. Whole-image inference is the only fixed point, so the result equals
it to float rounding. Why one collecting run is nearly enough: a tile's own mean
errs by ``μ_t − μ``, and over the image those errors average out (``Σ area_t (μ_t − μ)
≈ 0``), so the collected means are off only to second order (one more run when the
attention depends strongly on the image).

The cost is one extra, partial run over the tiles (the paper network: about 1.3×
the single-pass time); the memory is the single pass's. MST++ chains 15 attention
layers, each one's statistic moved by those before it: its runs settle one order of
magnitude each, in 3-5 runs. Other global operations (non-local blocks, whose
pixel-by-pixel affinity is no fixed-size sum) cannot be assembled this way: ``"auto"`` then gives each tile its own statistics, ``"image"`` refuses the
network rather than answer approximately, and ``"tile"`` always uses each tile's own
(the fastest). ONNX graphs: :mod:`mehs.ssr.tiling_onnx`.
"""

from __future__ import annotations

import os
import warnings
from typing import Callable

import numpy as np

from mehs.errors import InputError
from mehs.ssr.tiling_blend import TilingPlan, predict_tiled, tile_starts

#: Relative agreement of the means given to and measured by a run that ends it.
IMAGE_MEANS_TOL = 1e-5
#: Runs over the tiles (the first only collects) after which unsettled statistics stop
#: unless they are still settling (:func:`go_on`). Channel attention settles in 2-3; a
#: trained-like MST++ (15 attention layers in sequence, each one's statistic moved by the
#: ones before) in 4-5, each run gaining about an order of magnitude.
MAX_RUNS = 6
#: ``model.tiling["statistics"]`` values.
STATISTICS = ("auto", "image", "tile")


def statistics_mode(opts: dict) -> str:
    """``opts["statistics"]`` (removed from ``opts``), else ``MEHS_TILE_STATISTICS``, else "auto"."""
    mode = opts.pop("statistics", None)
    if mode is None:
        mode = os.environ.get("MEHS_TILE_STATISTICS", "").strip() or "auto"
    if mode not in STATISTICS:
        raise InputError(f"tiling statistics must be one of {STATISTICS}, got {mode!r} "
                         "(model.tiling['statistics'] or MEHS_TILE_STATISTICS)")
    return mode


def warn_tiles_differ(model, why: str) -> None:
    """Say that tiles run with their own statistics and so differ from the whole image
    (statistics "auto" on a network whose global operations tiles cannot assemble):
    ~1e-5 of the range for AWAN's attention, 3e-2 for an ONNX MST++'s channel
    similarity. Silent where the user asked for per-tile statistics."""
    model.__dict__.setdefault("_tiling_last", {})["tiles_differ"] = True
    warnings.warn(f"{getattr(model, 'name', 'model')}: {why}, so its tiles use their own "
                  "statistics and differ from whole-image inference; with more memory "
                  "(MEHS_TILE_MEMORY) fewer tiles, with tiling 'off' none; statistics "
                  "'tile' says this is wanted", RuntimeWarning, stacklevel=4)


def owned_spans(n: int, tile: int, plan: TilingPlan) -> dict[int, tuple[int, int, bool]]:
    """Per tile origin along an axis of ``n``: the span ``[lo, hi)`` it owns, and whether it is last.

    The spans partition ``[0, n)`` (the last runs on into the padding); each split is
    the multiple of ``plan.align`` nearest the middle of the overlap that lies at least
    ``plan.margin`` inside both tiles.
    """
    starts = tile_starts(n, tile, plan.overlap, plan.align)
    ends = [n if k == len(starts) - 1 else s + tile for k, s in enumerate(starts)]
    cuts = [0]
    for k in range(len(starts) - 1):
        lo, hi = starts[k + 1] + plan.margin, ends[k] - plan.margin
        a = plan.align
        mid = (starts[k + 1] + ends[k]) / 2
        c = int(round(mid / a)) * a
        if not lo <= c <= hi:
            c = -(-lo // a) * a
        if not lo <= c <= hi:
            raise InputError(f"tiles at {starts[k]} and {starts[k + 1]} overlap by "
                             f"{ends[k] - starts[k + 1]} px: no multiple of the {a}-pixel grid "
                             f"lies {plan.margin} px inside both; image-wide statistics need a "
                             f"blend of at least {a} px")
        cuts.append(c)
    cuts.append(n)
    return {s: (cuts[k], cuts[k + 1], k == len(starts) - 1) for k, s in enumerate(starts)}


def tile_windows(rows: dict, cols: dict, plan: TilingPlan, h: int, w: int):
    """``(y0, y1, x0, x1)`` of every tile in raster order, from :func:`owned_spans` of
    both axes (an axis's last tile runs to the image's edge), as
    :func:`mehs.ssr.tiling_blend.predict_tiled` visits them."""
    for y0 in rows:
        y1 = h if rows[y0][2] else y0 + plan.tile
        for x0 in cols:
            yield y0, y1, x0, (w if cols[x0][2] else x0 + plan.width)


def go_on(run: int, max_runs: int | None, statistics: int, change: float,
          before: float) -> bool:
    """Whether run ``run`` over the tiles, unsettled (``change``; the run before it:
    ``before``), is followed by another.

    A statistic of a forward depends only on the statistics before it, so the first run
    collects the first one exactly, the second the second one, and after one run per
    statistic plus one every statistic is the whole image's: a 4-level MST++ (9
    attention layers) with sharp attention still moved by 6e-3 after :data:`MAX_RUNS`
    runs. So past :data:`MAX_RUNS` the runs go on up to that number while the change
    still falls (a network that does not settle is not run a hundred times: the paper
    network has ~45 channel attentions). An explicit ``max_runs`` is a hard limit.
    """
    if max_runs is not None:
        return run < max_runs
    if run < MAX_RUNS:
        return True
    return run < statistics + 1 and change < before


def warn_unsettled(change: float, max_runs: int) -> None:
    """The warning of a run over the tiles whose image-wide means did not settle."""
    warnings.warn(f"tiled inference: the image-wide statistics (pooling means, attention "
                  f"similarities) still moved by {change:.1e} (relative) after {max_runs} runs; "
                  "the output may differ from whole-image inference by about as much",
                  RuntimeWarning, stacklevel=3)


def predict_tiled_image_means(fn: Callable[[np.ndarray], np.ndarray], rgb: np.ndarray,
                              plan: TilingPlan, *, tol: float = IMAGE_MEANS_TOL,
                              max_runs: int | None = None, record: dict | None = None,
                              multiple: int = 1) -> np.ndarray:
    """:func:`mehs.ssr.tiling_blend.predict_tiled` with image-wide pooling means.

    ``fn`` must run a torch network whose global poolings go through
    :func:`mehs.ssr.net.pooling.pooled_mean`, in this thread. Returns float32
    ``(H, W, B)``. Warns when the means have not settled to ``tol`` after ``max_runs``
    runs (default: :func:`go_on`'s rule; the last run's output is returned). ``record``
    receives ``image_runs`` (runs over the tiles, the collecting one included) and ``image_means_change`` (the last
    run's relative change of the means). ``multiple``: ``fn`` reflect-pads each tile to
    multiples of it (:func:`mehs.ssr.tiling_pad.padded`), which the pooled maps then cover.
    """
    # torch only here: tiling.py imports this module for ONNX models too
    from mehs.ssr.net.pooling import ImageMeans, PoolingsCollected

    record = {} if record is None else record
    if plan.tile is None:
        return np.asarray(fn(rgb), dtype=np.float32)
    if max_runs is not None and max_runs < 2:
        raise InputError(f"image-wide means need at least 2 runs over the tiles, got {max_runs}")
    h, w = rgb.shape[:2]
    rows, cols = owned_spans(h, plan.tile, plan), owned_spans(w, plan.width, plan)
    means = ImageMeans(multiple)

    def enter(y0: int, y1: int, x0: int, x1: int, stop_early: bool = False) -> None:
        ry, rx = rows[y0], cols[x0]
        means.enter((y0, y1), (x0, x1), ry[:2], rx[:2], ry[2], rx[2], stop_early=stop_early)

    change = float("inf")
    with means.active():
        # a crop of a few pooling cells shows where a forward's last pooling is
        s = max(plan.align, multiple) * 4
        means.learn_last(lambda: fn(np.ascontiguousarray(rgb[:min(h, s), :min(w, s)])))
        for y0, y1, x0, x1 in tile_windows(rows, cols, plan, h, w):   # outputs not kept
            enter(y0, y1, x0, x1, stop_early=True)
            try:
                fn(np.ascontiguousarray(rgb[y0:y1, x0:x1]))
            except PoolingsCollected:          # nothing after the last pooling is needed
                pass
        means.finish()
        statistics = len(means.collected())
        run, before = 1, float("inf")
        while go_on(run, max_runs, statistics, change, before):
            run, before = run + 1, change
            # (the last run's output is not kept while the next is made: one image-sized
            # array, 0.26 GB at 2048×1024, more from the third run on)
            out = None
            out = predict_tiled(fn, rgb, plan, on_tile=enter)
            change = means.finish()
            record.update(image_runs=run, image_means_change=change)
            if change <= tol:
                return out
    warn_unsettled(change, run)
    return out
