"""Tiled inference of SSR networks: overlapping tiles, seams blended, tile size from memory.

A fully convolutional network's output at a pixel depends only on the input
within its receptive field, so an image can be converted tile by tile: each
tile is run with a ``margin`` of context at every edge shared with a
neighbour, the margin's outputs get zero weight, and a linear ramp of
``blend`` pixels beyond it cross-fades neighbouring tiles. Where the margin
covers the receptive field the result equals whole-image inference (to
float32 rounding); the peak memory is that of one tile instead of the image
(one 2048×1024 image through the small FC-DenseNet held 7.5 GB, issue 16).

Exactness also needs the tiles to sit on the network's pooling grid: tile
origins and sizes are multiples of ``align`` (``2**depth`` for a U-Net that
pools ``depth`` times, so each tile's pooling windows are the whole image's),
and the margin covers the receptive field of every phase on that grid.

Memory. A call's memory is modelled as ``fixed + bytes_per_pixel × pixels``,
measured on two small probes (:func:`torch_memory_probe`; ``+ bytes_per_column ×
width`` for a network that streams its rows, as HSCNN-D does). By default the
process is to stay under :data:`DEFAULT_MAX_RSS` of resident memory: what it
already holds and the stitched output are taken off, the rest (at most
:data:`AVAILABLE_SHARE` of the available memory) is the tile's. Images whose
whole inference fits run whole, exactly as before; the others get the tile
shape that computes the fewest pixels (margins included) within the budget.
Tiles run with glibc's heap kept for reuse (:func:`mehs.ssr.allocator.reused_heap`:
no tensor page is faulted in twice), planned for that allocator's larger resident
memory per counted byte.

Global operations. A network with one is not tile-invariant: the channel
attention of :mod:`mehs.ssr.net.layers` averages each feature map over the whole
input (squeeze-and-excitation), and MST++'s spectral-wise attention compares channels
over all pixels, so a tile with its own statistics would differ from whole-image
inference. Both are sums over pixels: the tiles run with the whole image's instead,
at the cost of one or more further runs over the tiles (:mod:`mehs.ssr.tiling_global`,
:mod:`mehs.ssr.tiling_torch`; ``{"statistics": "tile"}`` turns it off). Other global
operations (AWAN's non-local blocks) keep each tile's own: the ramp hides the seams,
and large tiles (as large as the memory budget allows) keep the statistics close.
ONNX graphs get image-wide average poolings, rebuilt to take and report their
means and probed once (:mod:`mehs.ssr.tiling_onnx`); other statistics stay each tile's.

Size multiples. A network that takes only sizes divisible by ``k`` (a model's
``size_multiple``, or ``model.tiling["size_multiple"]``) gets every call, whole
image, tile or probe, reflect-padded to the multiple and its output cropped back
(:mod:`mehs.ssr.tiling_pad`); the tile grid becomes a multiple of ``k``.

Shapes: ``rgb`` float32 ``(H, W, 3)``; the per-tile function maps ``(h, w, 3)``
to ``(h, w, B)``; the result is float32 ``(H, W, B)`` (band-major in memory
when the tiles' outputs are, as torch's are).

References
----------
- Ronneberger, O., Fischer, P. and Brox, T. (2015). U-Net: Convolutional
  networks for biomedical image segmentation. MICCAI (the overlap-tile strategy).
- Luo, W., Li, Y., Urtasun, R. and Zemel, R. (2016). Understanding the effective
  receptive field in deep convolutional neural networks. NeurIPS.
"""

from __future__ import annotations

import os
import time
from typing import Callable

import numpy as np

from mehs.errors import InputError
from mehs.ssr.allocator import (ALLOCATOR_OVERHEAD, HEAP_PIXELS,  # noqa: F401 (public here)
                                allocator_overhead, heap_reuse_available, heap_reuse_overhead,
                                reused_heap)
from mehs.ssr.allocator import trim_heap as _trim_heap
from mehs.ssr.tiling_blend import (TilingPlan, _covered,  # noqa: F401 (public here)
                                   predict_tiled, tile_starts)
from mehs.ssr.tiling_global import statistics_mode
from mehs.ssr.tiling_pad import grid, size_multiple
from mehs.ssr.tiling_probes import (GLOBAL_MARGIN, MEMORY_PROBES,  # noqa: F401 (public here)
                                    PROBE_CHUNK_SHARE, _round_up, torch_align,
                                    torch_bytes_per_pixel, torch_memory_probe,
                                    torch_receptive_radius)

#: Peak resident memory of the whole process the default budget keeps under: a
#: laptop-sized 2 GB (issue 16: a 2048×1024 image through the small hdrssr net).
DEFAULT_MAX_RSS = 2_000_000_000
#: Share of the currently available memory the inference may use at most.
AVAILABLE_SHARE = 0.5
#: The least memory a budget gives a tile even when the process already holds
#: more than :data:`DEFAULT_MAX_RSS` (the cap then cannot be kept; small tiles do).
MIN_BUDGET = 256 << 20
#: Pixels of the linear ramp that cross-fades neighbouring tiles, unless given.
DEFAULT_BLEND = 16


def available_memory() -> int:
    """Bytes of memory available to new allocations now (``MemAvailable``), or 4 GiB if unknown."""
    try:
        import psutil

        return int(psutil.virtual_memory().available)
    except ImportError:
        pass
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except OSError:
        pass
    return 4 << 30


def _rss() -> int:
    """Resident memory of this process now (bytes)."""
    try:
        import psutil

        return int(psutil.Process().memory_info().rss)
    except ImportError:
        with open("/proc/self/statm") as f:
            return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE")


def default_budget(max_rss: int | None = None) -> int:
    """Bytes the next inference may use: ``max_rss`` minus what the process holds now.

    ``max_rss`` defaults to :data:`DEFAULT_MAX_RSS`; the result is at most
    :data:`AVAILABLE_SHARE` of the available memory and, when the process
    already holds nearly the cap or more, :data:`MIN_BUDGET` (at most the cap).
    """
    cap = DEFAULT_MAX_RSS if max_rss is None else int(max_rss)
    _trim_heap()
    share = AVAILABLE_SHARE * available_memory()
    return int(min(max(cap - _rss(), min(MIN_BUDGET, cap)), share))


def probe_budget(opts: dict) -> int:
    """Bytes a tiling probe may use: the ``max_bytes`` of ``model.tiling`` (``opts``), else
    ``MEHS_TILE_MEMORY``, else :func:`default_budget` under its ``max_rss``."""
    return int(opts.get("max_bytes") or env_max_bytes() or default_budget(opts.get("max_rss")))


def plan_tiles(shape: tuple[int, int], bytes_per_pixel: float, *, margin: int,
               blend: int = DEFAULT_BLEND, align: int = 8, max_bytes: int | None = None,
               fixed_bytes: float = 0.0, out_bytes: float = 0.0,
               overhead: Callable[[float], float] | None = None,
               column_bytes: float = 0.0) -> TilingPlan:
    """The tile shape that computes the fewest pixels within the memory budget.

    One call on ``rows × cols`` pixels is taken to need ``fixed_bytes +
    bytes_per_pixel × rows·cols + column_bytes × cols``, times ``overhead(rows·cols)`` if
    given (see :func:`allocator_overhead`).
    The image runs whole if that fits ``max_bytes``; otherwise tiles must fit
    ``max_bytes − out_bytes`` (the stitched output is held while they run).
    Every tile recomputes its neighbours' overlap (``2 margin + blend``), so the
    shape matters: all aligned tile heights are tried, each with the tile
    width (up to the widest the budget allows) that computes the fewest pixels
    across the image; strips (a tile spanning the image's height or width) are
    among them. Ties go to fewer tiles, then to the smaller tile.

    Parameters
    ----------
    shape
        ``(H, W)`` of the image.
    bytes_per_pixel, fixed_bytes, column_bytes
        Memory model of one call (see :func:`torch_memory_probe`; ``column_bytes``: a
        network streaming its rows, whose window is as wide as its input).
    margin, blend, align
        See :class:`TilingPlan`.
    max_bytes
        Memory the inference may use; default :func:`default_budget`.
    out_bytes
        Memory of the stitched output (``H × W × bands × 4``).
    overhead
        Resident bytes per modelled byte as a function of a call's pixels.
    """
    if bytes_per_pixel <= 0 or not np.isfinite(bytes_per_pixel):
        raise InputError(f"bytes_per_pixel must be positive, got {bytes_per_pixel}")
    if margin < 0 or blend < 0 or align < 1:
        raise InputError(f"margin and blend must be ≥ 0 and align ≥ 1, got "
                         f"{margin}, {blend}, {align}")
    if max_bytes is None:
        max_bytes = default_budget()
    h, w = shape

    def memory(rows: float, cols: float) -> float:
        return call_bytes(rows, cols, bytes_per_pixel, fixed_bytes, column_bytes, overhead)

    if memory(h, w) <= max_bytes:
        return TilingPlan(None, margin, blend, align)

    def fits(rows: int, cols: int) -> bool:
        return memory(rows, min(cols, w)) + out_bytes <= max_bytes

    if column_bytes:
        def widest(rows: int) -> int:
            return w if fits(rows, w) else _widest(fits, rows, w)
    else:
        # memory a function of the pixels alone: the most a tile may have, once
        lo, hi = 0.0, float(h * w)
        for _ in range(60):
            mid = 0.5 * (lo + hi)
            lo, hi = (mid, hi) if memory(mid, 1.0) + out_bytes <= max_bytes else (lo, mid)

        def widest(rows: int, max_px: float = lo) -> int:
            return int(max_px // rows)
    overlap = 2 * margin + blend
    # a tile must keep some weighted core beyond its two margins and the ramp
    smallest = _round_up(overlap + align, align)
    # (an axis shorter than that is one tile long: no overlap along it)
    if widest(min(smallest, h)) < min(smallest, w):
        need = memory(min(smallest, h), min(smallest, w)) + out_bytes
        raise InputError(f"a {smallest}-pixel tile (margin {margin}) needs "
                         f"{need / 2**20:.0f} MiB with the output, more than the "
                         f"{max_bytes / 2**20:.0f} MiB budget; give a smaller margin or "
                         "more memory")
    # per width limit, the width that covers the image's width with the fewest pixels
    best_w, cur = [], None
    for tw in range(smallest, max(_round_up(w, align), smallest) + 1, align):
        c = (_covered(w, tw, overlap, align), len(tile_starts(w, tw, overlap, align)), tw)
        cur = c if cur is None or c[:2] < cur[:2] else cur
        best_w.append(cur)
    best, top = None, max(_round_up(w, align), smallest)
    for th in range(smallest, max(_round_up(h, align), smallest) + 1, align):
        rows = min(th, h)
        fit = widest(rows)
        # a tile as wide as the image needs only its w columns, whatever the grid
        limit = top if fit >= w else min(fit // align * align, top)
        if limit < smallest:
            break
        cov_w, n_w, tw = best_w[(limit - smallest) // align]
        cost = (_covered(h, th, overlap, align) * cov_w,
                len(tile_starts(h, th, overlap, align)) * n_w, rows * min(tw, w))
        if best is None or cost < best[0]:
            best = (cost, th, tw)
        if th >= h:
            break
    _, th, tw = best
    return TilingPlan(th, margin, blend, align, tw)


def call_bytes(rows: float, cols: float, bytes_per_pixel: float, fixed_bytes: float = 0.0,
               column_bytes: float = 0.0,
               overhead: Callable[[float], float] | None = None) -> float:
    """The memory model of one call on ``rows × cols`` pixels (see :func:`plan_tiles`)."""
    n = rows * cols
    return ((fixed_bytes + bytes_per_pixel * n + column_bytes * cols)
            * (1.0 if overhead is None else overhead(n)))


def _widest(fits: Callable[[int, int], bool], rows: int, w: int) -> int:
    """The most columns (under ``w``, which does not fit) a tile of ``rows`` rows may have
    (memory grows with its columns)."""
    lo, hi = 0, w
    while hi - lo > 1:
        mid = (lo + hi) // 2
        lo, hi = (mid, hi) if fits(rows, mid) else (lo, mid)
    return lo


def plan_summary(shape: tuple[int, int], plan: TilingPlan) -> dict:
    """``{"tile": (h, w), "tiles": n, "computed": pixels computed / image pixels}``."""
    h, w = shape
    if plan.tile is None:
        return {"tile": (h, w), "tiles": 1, "computed": 1.0}
    ov, a = plan.overlap, plan.align
    n = len(tile_starts(h, plan.tile, ov, a)) * len(tile_starts(w, plan.width, ov, a))
    computed = _covered(h, plan.tile, ov, a) * _covered(w, plan.width, ov, a) / (h * w)
    return {"tile": (min(plan.tile, h), min(plan.width, w)), "tiles": n, "computed": computed}


# ------------------------------------------------------------- torch networks
def env_max_bytes() -> int | None:
    """``MEHS_TILE_MEMORY`` (MiB) if set: the user's cap on one tile's inference memory."""
    v = os.environ.get("MEHS_TILE_MEMORY")
    if not v:
        return None
    try:
        return int(float(v) * 2**20)
    except ValueError:
        raise InputError(f"MEHS_TILE_MEMORY must be a number of MiB, got {v!r}") from None


#: Images up to this many pixels always run whole, without a probe (any SSR
#: network of a sensible size converts 256×256 in well under the budget).
SMALL_IMAGE = 256 * 256


def tiled_network_call(model, fn: Callable[[np.ndarray], np.ndarray], rgb: np.ndarray,
                       probes: dict[str, Callable[[], object]],
                       image_means: Callable[..., np.ndarray] | None = None) -> np.ndarray:
    """The hook of the torch / ONNX SSR models: run ``fn`` whole or in tiles.

    ``model.tiling`` selects: ``"auto"`` (the default; tiles only when the image
    would exceed the memory budget), ``"off"`` (always whole), or a dict of
    options: :func:`plan_tiles` keywords (``bytes_per_pixel``, ``fixed_bytes``,
    ``margin``, ``blend``, ``align``, ``max_bytes``: the memory of one tile) and
    ``max_rss`` (the process cap of :func:`default_budget`) and ``statistics``
    (also ``MEHS_TILE_STATISTICS``; :mod:`mehs.ssr.tiling_global`): ``"auto"`` (the
    default) and ``"image"`` call ``image_means(fn, rgb, plan, strict)``, which
    stitches the tiles with image-wide global-pooling means where the network allows
    (equal to whole-image inference; ``strict``: refuse a network that does not),
    ``"tile"`` gives each tile its own, and ``size_multiple`` (see
    :mod:`mehs.ssr.tiling_pad`: ``fn`` must already pad to it; here the tile grid is
    made a multiple of it, and a margin whose overlap ``2 margin + blend`` is under
    ``k − 1`` is raised, so an axis's last tile is at least ``k`` long). Missing ones come
    from ``probes[name]()``, each called at most once per model (cached in
    ``model._tiling_probe``) and only when needed: the memory probe (a number,
    or a dict as :func:`torch_memory_probe` returns) for images above
    :data:`SMALL_IMAGE`, the margin and grid probes only when the image is
    actually tiled. ``MEHS_TILE_MEMORY`` (MiB) sets ``max_bytes``; without it the
    budget is :func:`default_budget` less the stitched output. ``probes["check_tiles"]``
    (optional): given the call's record after the tiles ran, whether to check the plan on
    a probe image (:mod:`mehs.ssr.tiling_check`). What was done is left in
    ``model._tiling_last`` (plan, budget, seconds spent probing, the check's difference).
    """
    mode = getattr(model, "tiling", "auto")
    if mode == "off" or mode is None:
        return fn(rgb)
    if mode != "auto" and not isinstance(mode, dict):
        raise InputError(f"tiling must be 'auto', 'off' or a dict of options, got {mode!r}")
    opts = dict(mode) if isinstance(mode, dict) else {}
    statistics = statistics_mode(opts)
    opts.pop("size_multiple", None)
    k = size_multiple(model)
    if mode == "auto" and rgb.shape[0] * rgb.shape[1] <= SMALL_IMAGE:
        return fn(rgb)
    t0 = time.perf_counter()
    release = getattr(model, "release_memory", None)
    if release is not None:
        # memory an ONNX arena keeps from earlier runs is reusable: returned before the
        # memory probe and the budget measure what the process holds
        release()
    tile_budget = opts.pop("max_bytes", None)
    if tile_budget is None:
        tile_budget = env_max_bytes()
    max_rss = opts.pop("max_rss", None)
    cache = model.__dict__.setdefault("_tiling_probe", {})

    def get(name):
        if name in opts:
            return opts.pop(name)
        if name not in cache:
            cache[name] = probes[name]()
        return cache[name]

    if "bytes_per_pixel" in opts:
        memory = {"bytes_per_pixel": opts.pop("bytes_per_pixel")}
    else:
        if "bytes_per_pixel" not in cache:
            m = probes["bytes_per_pixel"]()
            cache.update(m if isinstance(m, dict) else {"bytes_per_pixel": m})
        memory = cache
    bpp = float(memory["bytes_per_pixel"])
    fixed = float(opts.pop("fixed_bytes", memory.get("fixed_bytes", 0.0)))
    h, w = rgb.shape[:2]
    # (a network streaming its rows holds a window as wide as its input)
    column = float(opts.pop("column_bytes", memory.get("bytes_per_column", 0.0)))
    if tile_budget is not None:
        budget, out_bytes = int(tile_budget), 0.0
    else:
        budget = default_budget(max_rss)
        out_bytes = float(memory.get("out_bytes_per_pixel", 0.0)) * h * w
    record = {"budget": budget, "out_bytes": out_bytes, "max_rss": max_rss}
    model.__dict__["_tiling_last"] = record
    overhead = allocator_overhead if memory.get("allocator") == "heap" else None
    if call_bytes(h, w, bpp, fixed, column, overhead) <= budget:
        record.update(plan=None, summary=plan_summary((h, w), TilingPlan(None, 0, 0, 1)),
                      probe_seconds=time.perf_counter() - t0)
        return fn(rgb)
    # tiles other than an axis's last must need no padding: on a grid of the multiple
    align = grid(get("align"), k)
    margin = get("margin")
    blend = opts.get("blend", DEFAULT_BLEND)
    if (k > 1 and isinstance(blend, (int, float)) and isinstance(margin, (int, float))
            and margin >= 0 and blend >= 0 and 2 * margin + blend < k - 1):
        # an axis's last tile is longer than the overlap (tile_starts): at least k long,
        # its reflect padding is the image's own (tiles that do not overlap could leave
        # a 1-pixel last tile, which np.pad would reflect within itself); the margin, not
        # the blend, grows: more context leaves the output unchanged
        margin = int(np.ceil((k - 1 - blend) / 2))
    wide = statistics != "tile" and image_means is not None
    if wide:
        # image-wide means split the overlaps on the grid at a margin from both tiles'
        # edges: a margin on the grid always leaves such a split (probed margins are)
        margin = _round_up(margin, align)
    if tile_budget is None:
        budget = default_budget(max_rss)            # after the margin probe's garbage
    # tiles on the C heap (no page faulted in twice: 1.7-1.9x faster per pixel here),
    # planned for its larger resident memory per counted byte; the default allocator
    # if the budget cannot hold a tile that way
    plan, reuse = None, overhead is not None and heap_reuse_available()
    if reuse:
        try:
            plan = plan_tiles((h, w), bpp, margin=margin, align=align, max_bytes=budget,
                              fixed_bytes=fixed, out_bytes=out_bytes, column_bytes=column,
                              overhead=heap_reuse_overhead, **opts)
        except InputError:
            reuse = False
    if plan is None:
        plan = plan_tiles((h, w), bpp, margin=margin, align=align, max_bytes=budget,
                          fixed_bytes=fixed, out_bytes=out_bytes, column_bytes=column,
                          overhead=overhead, **opts)
    record.update(budget=budget, plan=plan, summary=plan_summary((h, w), plan),
                  heap_reuse=reuse, probe_seconds=time.perf_counter() - t0)
    record["statistics"] = "tile"
    if statistics == "image" and image_means is None:
        raise InputError("image-wide tiling statistics need a torch network or an ONNX "
                         "model file (a bare function's poolings cannot be reached); use "
                         "statistics 'tile'")
    tiles = fn
    if plan.tile is not None and reuse:
        # (only the heap kept for reuse holds what a trim returns)
        th, tw = min(plan.tile, h), min(plan.width, w)
        need = call_bytes(th, tw, bpp, fixed, column, heap_reuse_overhead)
        # (a budget for one tile leaves the stitched output out: the process holds it too)
        held = 0.0 if tile_budget is None else float(memory.get("out_bytes_per_pixel", 0.0)) * h * w
        try:
            tiles = _heap_guard(fn, _rss() + budget + held, need, record)
        except OSError:                 # no way to read the resident memory here: unguarded
            pass
    with reused_heap(reuse):
        if wide:
            out = image_means(tiles, rgb, plan, statistics == "image")
        else:
            out = predict_tiled(tiles, rgb, plan)
    check = probes.get("check_tiles")
    if check is not None and statistics != "tile" and not record.get("tiles_differ") \
            and check(record):
        from mehs.ssr.tiling_check import check_tiles

        def run(x: np.ndarray, p: TilingPlan) -> np.ndarray:
            if record.get("statistics") == "image":
                return image_means(fn, x, p, False)
            return predict_tiled(fn, x, p)

        saved = dict(record)
        check_tiles(model, fn, plan, run, saved)
        model.__dict__["_tiling_last"] = saved        # the probe's run is not this call's
    return out


def _heap_guard(fn: Callable[[np.ndarray], np.ndarray], limit: float, need: float,
                record: dict) -> Callable[[np.ndarray], np.ndarray]:
    """``fn`` for tiles, returning the C heap's free memory to the system before a tile
    whose modelled ``need`` would take the process past ``limit`` bytes resident.

    The heap kept for reuse holds the blocks earlier tiles freed, in holes that later
    ones do not always fit: over a run of tiles (and an image-wide means' collecting
    run before them) the paper network's full preset grew to 2.8x a tile's counted
    bytes and passed a 1.5 GB cap by 0.3 GB. Trimming costs the next tile its page
    faults, so it happens only where the budget is short. ``record["heap_trims"]``
    counts the trims.
    """
    record["heap_trims"] = 0

    def guarded(x: np.ndarray) -> np.ndarray:
        try:
            over = _rss() + need > limit
        except OSError:
            over = False
        if over:
            _trim_heap()
            record["heap_trims"] += 1
        return fn(x)

    return guarded


#: The margin and grid of an ONNX graph that cannot be measured (the ``onnx`` package
#: missing, a bare function): they cover the small and tiny mehs networks (margins 56
#: and 16 px on grids of 8) and U-Nets up to 5 poolings with short fields; an
#: :class:`~mehs.ssr.models.OnnxModel` is measured (:mod:`mehs.ssr.tiling_onnx_probes`).
ONNX_DEFAULT_MARGIN, ONNX_DEFAULT_ALIGN = 64, 32


def tiled_onnx_call(model, fn: Callable[[np.ndarray], np.ndarray], rgb: np.ndarray) -> np.ndarray:
    """An ONNX model's whole-image ``fn`` on ``rgb``, tiled when large.

    Memory per pixel is measured once: the growth of the process's resident
    memory over a 256×256 probe run (256 rounded up to the model's size multiple;
    onnxruntime's arena keeps its peak), with a floor of 1 kB per pixel in case the
    arena was already grown by earlier calls. ``fn`` pads to the size multiple itself.
    """
    def memory() -> dict:
        n = _round_up(256, size_multiple(model))
        _trim_heap()
        before = _rss()
        y = fn(np.zeros((n, n, 3), dtype=np.float32))
        return {"bytes_per_pixel": max(1024.0, 1.25 * max(0, _rss() - before) / n ** 2),
                "out_bytes_per_pixel": 4.0 * y.shape[-1]}

    stitcher = None
    if hasattr(model, "session") and hasattr(model, "path"):     # an OnnxModel
        from mehs.ssr.tiling_onnx import onnx_image_means_stitcher

        stitcher = onnx_image_means_stitcher(model)
    if hasattr(model, "session") and hasattr(model, "path"):
        from mehs.ssr.tiling_onnx_probes import onnx_tiling_probes

        given = getattr(model, "tiling", None)
        probes = onnx_tiling_probes(model, memory, given if isinstance(given, dict) else {})
        # graphs tiled with image-wide means were checked on a probe already
        probes["check_tiles"] = lambda record: record.get("statistics") == "tile"
    else:       # a graph behind a bare function cannot be rebuilt to measure
        probes = {"bytes_per_pixel": memory, "margin": lambda: ONNX_DEFAULT_MARGIN,
                  "align": lambda: ONNX_DEFAULT_ALIGN}
    return tiled_network_call(model, fn, rgb, probes, image_means=stitcher)


def __getattr__(name: str):
    # the torch hook lives in mehs.ssr.tiling_torch (which imports this module);
    # the old import path keeps working without an import cycle
    if name == "tiled_torch_call":
        from mehs.ssr.tiling_torch import tiled_torch_call

        return tiled_torch_call
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
