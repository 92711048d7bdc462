"""A check of the tiling plan on a probe image before the real tiles run (issue 16).

The probes of :mod:`mehs.ssr.tiling_probes` and :mod:`mehs.ssr.tiling_grid` read a
network's receptive field and down-sampling grid; tiles on that grid, with that margin,
equal whole-image inference only if the network is also *shift-equivariant* on its grid.
Some are not, and no field or shape shows it: a bilinear up-sampling to the input's size
with ``align_corners=True`` (older HRNet-style code) samples at positions that depend on
the whole image's size, and its tiles were 7.9e-2 of the range off, silently.

:func:`check_tiles` runs the plan on two probe images — two tiles side by side, and two
one above the other, on the plan's grid, margin and blend, as large as the plan's where a
probe fits one tile's pixels — and compares them with the whole probe images; a
difference above :data:`CHECK_TOL` of the range (all but 0.1 % of the values) gives a
warning naming the model, on every call (measured once per model and plan shape).
mehs's own networks, whose tiles the test suite compares with whole images, skip it, as
do tiles that are known to differ (their own statistics).
"""

from __future__ import annotations

import warnings
from typing import Callable

import numpy as np

from mehs.ssr.tiling_blend import TilingPlan

#: Agreement the probe must show (relative to the range), by all but 0.1 % of its values:
#: a graph that divides by its output's X+Y+Z magnifies rounding at a few pixels.
CHECK_TOL, CHECK_QUANTILE = 1e-5, 0.999


def probe_image(h: int, w: int) -> np.ndarray:
    """Strong left-right and top-bottom contrast (a tile's own statistics differ from the
    image's), and brightness spanning two decades."""
    rng = np.random.default_rng(7)
    x = rng.gamma(1.0, 0.5, (h, w, 3)).astype(np.float32)
    x[:, : w // 3] *= 4.0
    x[: h // 2, :, 1] *= 0.2
    return x


def relative_difference(tiled: np.ndarray, whole: np.ndarray, *,
                        overwrite: bool = False) -> float:
    """``|tiled − whole| / max |whole|`` at :data:`CHECK_QUANTILE` (inf where not finite);
    ``overwrite``: in ``tiled``'s memory where it is float32 (a probe within a tile's).

    A quantile, not the largest: a graph that restores luminance itself divides by its
    output's X+Y+Z, and an untrained network's is near zero at a few pixels, which
    magnifies float rounding there; what makes tiles differ moves most values."""
    scale = float(np.abs(whole).max()) or 1.0
    inplace = overwrite and tiled.dtype == np.float32 and tiled.flags.writeable
    d = np.subtract(tiled, whole, out=tiled if inplace else None, dtype=np.float32)
    np.abs(d, out=d)
    d /= scale
    return float(np.quantile(d, CHECK_QUANTILE)) if np.isfinite(d).all() else float("inf")


def _probe_tiles(plan: TilingPlan) -> tuple[int, int] | None:
    """Tile height and width for the probes: the plan's own (a network may act on a
    tile's size), halved on the grid while a probe of two of them would need more pixels
    than one of the plan's tiles (the tile budget), down to the smallest tile on the grid;
    None where even that probe would need more than twice a tile."""
    a = plan.align
    smallest = -(-(plan.overlap + a) // a) * a
    th, tw = max(plan.tile, smallest), max(plan.width, smallest)
    budget = plan.tile * plan.width

    def pixels(th: int, tw: int) -> int:      # the larger of the two probes
        return max(th * (tw + (tw - plan.overlap) // a * a),
                   tw * (th + (th - plan.overlap) // a * a))

    while pixels(th, tw) > budget and max(th, tw) > smallest:
        th, tw = max(smallest, th // 2 // a * a), max(smallest, tw // 2 // a * a)
    return (th, tw) if pixels(th, tw) <= 2 * budget else None


def check_tiles(model, fn: Callable[[np.ndarray], np.ndarray], plan: TilingPlan,
                run: Callable[[np.ndarray, TilingPlan], np.ndarray],
                record: dict) -> float | None:
    """Compare ``run(probe, probe_plan)`` (the tiled path) with ``fn(probe)`` (whole) on two
    probes, two tiles of ``plan``'s grid, margin and blend side by side and two one above
    the other (a network may be shift-equivariant along one axis only); warn where they
    differ, on every call.

    Returns the difference (relative to the range, at :data:`CHECK_QUANTILE`), or None
    where the probe would need more than twice a tile's pixels (warned: the tiles are
    unchecked). Measured once per model and plan shape (``model._tiling_probe``:
    ``tiles_checked``, ``tiles_check_diff``); the call's ``record`` gets
    ``tiles_check_diff`` and, where they differ, ``tiles_differ``.
    """
    a = plan.align
    name = getattr(model, "name", "model")
    cache = model.__dict__.setdefault("_tiling_probe", {})
    key = [plan.margin, plan.blend, a, plan.tile, plan.width]
    if cache.get("tiles_checked") != key:
        sides = _probe_tiles(plan)
        diff = None
        if sides is not None:
            th, tw = sides
            diff = 0.0
            for h, w in ((th, tw + (tw - plan.overlap) // a * a),
                         (th + (th - plan.overlap) // a * a, tw)):
                rgb = probe_image(h, w)
                whole = np.asarray(fn(rgb), dtype=np.float32)
                # (no catch_warnings around it: its filters are the process's, and another
                # thread's warnings went unseen meanwhile)
                tiled = run(rgb, TilingPlan(th, plan.margin, plan.blend, a, tw))
                diff = max(diff, relative_difference(tiled, whole, overwrite=True))
                del rgb, whole, tiled
        cache["tiles_checked"], cache["tiles_check_diff"] = key, diff
    diff = cache["tiles_check_diff"]
    record["tiles_check_diff"] = diff
    if diff is None:
        warnings.warn(f"{name}: its tiles (margin {plan.margin}, grid {a}) could not be "
                      "checked against whole-image inference within the tile budget; they "
                      "are exact only if the network is shift-equivariant on its grid and "
                      "its field within the margin", RuntimeWarning, stacklevel=4)
    elif diff > CHECK_TOL:
        record["tiles_differ"] = True
        warnings.warn(f"{name}: on a probe image its tiles "
                      f"(margin {plan.margin}, grid {a}) differ from whole-image inference "
                      f"by {diff:.1e} of the range: it is not shift-equivariant on its grid "
                      "(a resampling to the image's size, align_corners=True?) or its field "
                      "reaches past the margin; tiled output may be off near the seams "
                      "(more memory, MEHS_TILE_MEMORY: fewer tiles; tiling 'off': none; "
                      "model.tiling = {'margin': …, 'align': …} to set them)",
                      RuntimeWarning, stacklevel=4)
    return diff
