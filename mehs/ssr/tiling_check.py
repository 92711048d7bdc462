"""A check of the tiling plan on a probe image before the real tiles run (issue 16).

The probes of :mod:`mehs.ssr.tiling_probes` and :mod:`mehs.ssr.tiling_grid` read a
network's receptive field and down-sampling grid; tiles on that grid, with that margin,
equal whole-image inference only if the network is also *shift-equivariant* on its grid.
Some are not, and no field or shape shows it: a bilinear up-sampling to the input's size
with ``align_corners=True`` (older HRNet-style code) samples at positions that depend on
the whole image's size, and its tiles were 7.9e-2 of the range off, silently.

:func:`check_tiles` runs the plan on a probe image — two tiles side by side, on the
plan's grid, margin and blend, as large as the plan's where that is small beside the
image — and compares it with the whole probe image; a
difference above :data:`CHECK_TOL` of the range (all but 0.1 % of the values) gives a
warning naming the model. Once per model and plan shape. mehs's own networks, whose
tiles the test suite compares with whole images, skip it, as do tiles that are known to
differ (their own statistics) and plans whose probe would not be small beside the image.
"""

from __future__ import annotations

import warnings
from typing import Callable

import numpy as np

from mehs.ssr.tiling_blend import TilingPlan

#: Agreement the probe must show (relative to the range), by all but 0.1 % of its values:
#: a graph that divides by its output's X+Y+Z magnifies rounding at a few pixels.
CHECK_TOL, CHECK_QUANTILE = 1e-5, 0.999
#: The largest probe, as a share of the image's pixels (with the whole probe and its two
#: tiles, about three times that is computed).
CHECK_SHARE = 0.1


def probe_image(h: int, w: int) -> np.ndarray:
    """Strong left-right and top-bottom contrast (a tile's own statistics differ from the
    image's), and brightness spanning two decades."""
    rng = np.random.default_rng(7)
    x = rng.gamma(1.0, 0.5, (h, w, 3)).astype(np.float32)
    x[:, : w // 3] *= 4.0
    x[: h // 2, :, 1] *= 0.2
    return x


def check_tiles(model, fn: Callable[[np.ndarray], np.ndarray], plan: TilingPlan,
                run: Callable[[np.ndarray, TilingPlan], np.ndarray],
                shape: tuple[int, int]) -> float | None:
    """Compare ``run(probe, probe_plan)`` (the tiled path) with ``fn(probe)`` (whole) on a
    probe of two tiles of ``plan``'s grid, margin and blend; warn where they differ.

    Returns the difference (relative to the range, at :data:`CHECK_QUANTILE`), or None
    where it was not checked (done before for this plan shape, or the probe would be more
    than :data:`CHECK_SHARE` of the ``shape`` image). Kept in ``model._tiling_probe``
    (``tiles_checked``, ``tiles_check_diff``).
    """
    a = plan.align
    cache = model.__dict__.setdefault("_tiling_probe", {})
    key = [plan.margin, plan.blend, a]
    if cache.get("tiles_checked") == key:
        return None
    # the plan's own tiles where they are small beside the image (a network may act on a
    # tile's size), else smaller ones on the grid, down to the smallest
    smallest = -(-(plan.overlap + a) // a) * a
    th, tw = max(plan.tile, smallest), max(plan.width, smallest)
    limit = CHECK_SHARE * shape[0] * shape[1]

    def pixels(th: int, tw: int) -> int:
        return th * (tw + (tw - plan.overlap) // a * a)

    while pixels(th, tw) > limit and max(th, tw) > smallest:
        th, tw = max(smallest, th // 2 // a * a), max(smallest, tw // 2 // a * a)
    if pixels(th, tw) > limit:
        return None
    rgb = probe_image(th, tw + (tw - plan.overlap) // a * a)
    whole = np.asarray(fn(rgb), dtype=np.float32)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)      # said once, below
        tiled = np.asarray(run(rgb, TilingPlan(th, plan.margin, plan.blend, a, tw)),
                           dtype=np.float32)
    scale = float(np.abs(whole).max()) or 1.0
    d = np.abs(tiled - whole) / scale
    diff = float(np.quantile(d, CHECK_QUANTILE)) if np.isfinite(d).all() else float("inf")
    cache["tiles_checked"], cache["tiles_check_diff"] = key, diff
    if diff > CHECK_TOL:
        warnings.warn(f"{getattr(model, 'name', 'model')}: on a probe image its tiles "
                      f"(margin {plan.margin}, grid {a}) differ from whole-image inference "
                      f"by {diff:.1e} of the range: it is not shift-equivariant on its grid "
                      "(a resampling to the image's size, align_corners=True?) or its field "
                      "reaches past the margin; tiled output may be off near the seams "
                      "(more memory, MEHS_TILE_MEMORY: fewer tiles; tiling 'off': none; "
                      "model.tiling = {'margin': …, 'align': …} to set them)",
                      RuntimeWarning, stacklevel=4)
    return diff
