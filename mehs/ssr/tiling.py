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
pools ``depth`` times, so each tile's pooling windows are the whole image's).

Limits. A network with a *global* operation is not tile-invariant: the
channel attention of :mod:`mehs.ssr.net.layers` averages each feature map over
the whole input (squeeze-and-excitation), so a tile sees its own averages and
the result differs slightly from whole-image inference; the ramp hides the
seams, and large tiles (the default: as large as the memory budget allows) keep
the averages close. Images that fit the budget are run whole, exactly as before.

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
from dataclasses import dataclass
from typing import Callable

import numpy as np

from mehs.errors import InputError

#: Default cap on the memory one tile's inference may use (a laptop-sized budget:
#: with torch, numpy, the input and the 31-band output the process stays under 2 GB).
DEFAULT_MAX_BYTES = 3 << 29
#: Share of the currently available memory a tile may use at most.
AVAILABLE_SHARE = 0.5


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


_MALLOC_TRIM = []


def _trim_heap() -> None:
    """Return the C heap's free memory to the system (glibc ``malloc_trim``; elsewhere nothing).

    glibc keeps freed blocks below its mmap threshold resident; after a network
    run that is up to a few hundred MB the next tile could reuse, but that the
    resident-memory figure counts as held.
    """
    if not _MALLOC_TRIM:
        fn = None
        try:
            import ctypes

            fn = ctypes.CDLL("libc.so.6").malloc_trim
            fn.argtypes, fn.restype = [ctypes.c_size_t], ctypes.c_int
        except (OSError, AttributeError):
            pass
        _MALLOC_TRIM.append(fn)
    if _MALLOC_TRIM[0] is not None:
        _MALLOC_TRIM[0](0)


def _round_up(n: int, a: int) -> int:
    return -(-n // a) * a


def plan_tiles(shape: tuple[int, int], bytes_per_pixel: float, *, margin: int, blend: int = 16,
               align: int = 8, max_bytes: int | None = None) -> TilingPlan:
    """Choose the tile shape that fits the memory budget and computes the fewest pixels.

    Every tile recomputes its neighbours' overlap, so the shape matters: for a
    2048×1024 image, a budget of ~0.5 M pixels and a 55-px margin, 584×896
    tiles compute 1.27× the image's pixels, 720×720 squares 1.34×. All aligned
    heights are tried, each with the widest tile the budget allows.

    Parameters
    ----------
    shape
        ``(H, W)`` of the image.
    bytes_per_pixel
        Peak memory of the network per input pixel (see :func:`torch_bytes_per_pixel`).
    margin, blend, align
        See :class:`TilingPlan`.
    max_bytes
        Memory budget of one tile; default ``min(DEFAULT_MAX_BYTES,
        AVAILABLE_SHARE × available memory)``.
    """
    if bytes_per_pixel <= 0 or not np.isfinite(bytes_per_pixel):
        raise InputError(f"bytes_per_pixel must be positive, got {bytes_per_pixel}")
    if margin < 0 or blend < 0 or align < 1:
        raise InputError(f"margin and blend must be ≥ 0 and align ≥ 1, got "
                         f"{margin}, {blend}, {align}")
    if max_bytes is None:
        max_bytes = int(min(DEFAULT_MAX_BYTES, AVAILABLE_SHARE * available_memory()))
    h, w = shape
    if h * w * bytes_per_pixel <= max_bytes:
        return TilingPlan(None, margin, blend, align)
    max_px = max_bytes / bytes_per_pixel
    # a tile must keep some weighted core beyond its two margins and the ramp
    smallest = _round_up(2 * margin + blend + align, align)
    if smallest * smallest > max_px:
        raise InputError(f"a {smallest}-pixel tile (margin {margin}) needs "
                         f"{smallest ** 2 * bytes_per_pixel / 2**20:.0f} MiB, more than the "
                         f"{max_bytes / 2**20:.0f} MiB budget; give a smaller margin or "
                         "more memory")
    overlap = 2 * margin + blend
    best = None
    for th in range(smallest, _round_up(h, align) + 1, align):
        tw = min(int(max_px // th) // align * align, _round_up(w, align))
        if tw < smallest:
            break
        cost = (_covered(h, th, overlap, align) * _covered(w, tw, overlap, align), -th * tw)
        if best is None or cost < best[0]:
            best = (cost, th, tw)
    _, th, tw = best
    return TilingPlan(th, margin, blend, align, tw)


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
        nz = np.flatnonzero(r)
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


def predict_tiled(fn: Callable[[np.ndarray], np.ndarray], rgb: np.ndarray, plan: TilingPlan
                  ) -> np.ndarray:
    """Run ``fn`` on overlapping tiles of ``rgb`` and blend the results.

    Parameters
    ----------
    fn
        ``(h, w, 3) → (h, w, B)`` float32, e.g. a network's whole-image call.
    rgb
        float32 ``(H, W, 3)``.
    plan
        From :func:`plan_tiles`; ``plan.tile is None`` runs the image whole.

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
            if out is not None:
                _trim_heap()                  # the last tile's freed blocks, before the next
            y = np.asarray(fn(np.ascontiguousarray(rgb[y0:y1, x0:x1])), dtype=np.float32)
            if y.ndim != 3 or y.shape[:2] != (y1 - y0, x1 - x0):
                raise InputError(f"the model turned a {y1 - y0}×{x1 - x0} tile into shape "
                                 f"{y.shape}; tiled inference needs (h, w, bands) out")
            if out is None:                   # zeros: pages are only touched as tiles land
                if y.transpose(2, 0, 1).flags.c_contiguous:
                    out = np.zeros((y.shape[2], h, w), dtype=np.float32).transpose(1, 2, 0)
                else:
                    out = np.zeros((h, w, y.shape[2]), dtype=np.float32)
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


# ------------------------------------------------------------- torch networks
def torch_bytes_per_pixel(network, *, probe: int = 64, safety: float = 1.0) -> float:
    """Peak-memory estimate per input pixel of a torch network, from one probe run.

    Sums the bytes of every leaf module's output on a ``probe × probe`` input
    (an upper bound without autograd: a dense network's concatenations keep
    many alive together, but not all), plus the input, times ``safety``.
    Small hdrssr net: 3.1 kB/px estimated; peak RSS growth of a whole
    1024×512 image measured 1.4 kB/px.
    """
    import torch

    total = [0]

    def hook(_m, _i, out):
        if isinstance(out, torch.Tensor):
            total[0] += out.numel() * out.element_size()

    leaves = [m for m in network.modules() if not any(True for _ in m.children())]
    handles = [m.register_forward_hook(hook) for m in leaves]
    try:
        param = next(network.parameters(), None)
        device = param.device if param is not None else "cpu"
        with torch.no_grad():
            network(torch.zeros(1, 3, probe, probe, device=device))
    finally:
        for hd in handles:
            hd.remove()
    return safety * (total[0] / probe ** 2 + 12)


def _global_pools_detached(network):
    """Context: the channel attention's global means detached from autograd (see below)."""
    import contextlib

    import torch

    @contextlib.contextmanager
    def ctx():
        patched = []
        for m in network.modules():
            if type(m).__name__ == "ChannelAttention":
                def local(x, _m=m):
                    s = x.mean(dim=(2, 3), keepdim=True).detach()
                    return x * torch.sigmoid(_m.excite(torch.relu(_m.squeeze(s))))
                m.forward = local          # an instance attribute shadows the method
                patched.append(m)
        try:
            yield
        finally:
            for m in patched:
                del m.forward
    return ctx()


#: Margin used when a network's gradient reaches the whole probe (a global
#: operation such as spectral-wise attention over all pixels, or a field wider
#: than the largest probe): tiles are then approximate whatever the margin.
GLOBAL_MARGIN = 64


def torch_receptive_radius(network, *, probe: int = 128, max_probe: int = 512,
                           align: int = 1) -> int:
    """Receptive-field radius (pixels) of a torch network's local part, measured by autograd.

    The gradient of an output pixel w.r.t. the input is non-zero exactly inside
    its receptive field. A global average (the channel attention of
    :mod:`mehs.ssr.net.layers`) would spread it over the whole probe, so its
    mean is detached during the probe: the radius is that of the convolutions,
    poolings and up-samplings. The probe doubles until the field fits inside it;
    a field still filling a ``max_probe`` probe (another global operation)
    gives :data:`GLOBAL_MARGIN`.

    With ``align > 1`` the result is the tile margin that makes tiles whose
    edges lie on that grid exact: behind a pooling the field depends on the
    pixel's phase on the grid (small hdrssr: 54 px right of a pixel at phase 0,
    59 px at phase 3). The gradient of the ``align × align`` block of outputs
    at an aligned centre bounds every phase at once: with ``L`` and ``R`` its
    field's reach left of and right of the block's first pixel, a pixel at
    phase ``p`` reaches at most ``L − p`` left and ``R − p`` right, so a margin
    of ``round_up(L, align)`` covers a tile's leading edge and
    ``round_up(R − align + 1, align)`` its trailing edge (both on the grid).
    """
    import torch

    param = next(network.parameters(), None)
    device = param.device if param is not None else "cpu"
    a = max(1, int(align))
    while True:
        x = torch.rand(1, 3, probe, probe, device=device, requires_grad=True)
        c = probe // 2 // a * a
        with _global_pools_detached(network):
            network(x)[0, :, c:c + a, c:c + a].sum().backward()
        g = x.grad[0].abs().sum(0).cpu().numpy()
        ys, xs = np.nonzero(g > 0)
        if ys.size == 0:
            return 0
        lo, hi = min(ys.min(), xs.min()), max(ys.max(), xs.max())
        if lo > 0 and hi < probe - 1:
            reach_lo, reach_hi = int(c - lo), int(hi - c)
            if a == 1:
                return max(reach_lo, reach_hi)
            return max(_round_up(reach_lo, a), _round_up(max(0, reach_hi - a + 1), a))
        if probe >= max_probe:
            return GLOBAL_MARGIN
        probe *= 2


def torch_align(network) -> int:
    """Tile grid of a torch network: ``2**depth`` of its deepest pooling stack (at least 8)."""
    depths = [int(getattr(m, "depth")) for m in network.modules()
              if isinstance(getattr(m, "depth", None), int)]
    return max([8] + [2 ** d for d in depths])


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
                       probes: dict[str, Callable[[], float]]) -> np.ndarray:
    """The hook of the torch / ONNX SSR models: run ``fn`` whole or in tiles.

    ``model.tiling`` selects: ``"auto"`` (the default; tiles only when the image
    would exceed the memory budget), ``"off"`` (always whole), or a dict of
    :func:`plan_tiles` keywords (``bytes_per_pixel``, ``margin``, ``blend``,
    ``align``, ``max_bytes``). Missing ones come from ``probes[name]()``, each
    called at most once per model (cached in ``model._tiling_probe``) and only
    when needed: the memory probe for images above :data:`SMALL_IMAGE`, the
    margin and grid probes only when the image is actually tiled.
    ``MEHS_TILE_MEMORY`` (MiB) caps the budget.
    """
    mode = getattr(model, "tiling", "auto")
    if mode == "off" or mode is None:
        return fn(rgb)
    if mode != "auto" and not isinstance(mode, dict):
        raise InputError(f"tiling must be 'auto', 'off' or a dict of options, got {mode!r}")
    opts = dict(mode) if isinstance(mode, dict) else {}
    if mode == "auto" and rgb.shape[0] * rgb.shape[1] <= SMALL_IMAGE:
        return fn(rgb)
    if "max_bytes" not in opts and env_max_bytes() is not None:
        opts["max_bytes"] = env_max_bytes()
    cache = model.__dict__.setdefault("_tiling_probe", {})

    def get(name):
        if name in opts:
            return opts.pop(name)
        if name not in cache:
            cache[name] = probes[name]()
        return cache[name]

    bpp = get("bytes_per_pixel")
    budget = {"max_bytes": opts["max_bytes"]} if "max_bytes" in opts else {}
    if plan_tiles(rgb.shape[:2], bpp, margin=0, **budget).tile is None:
        return fn(rgb)
    margin, align = get("margin"), get("align")
    plan = plan_tiles(rgb.shape[:2], bpp, margin=margin, align=align, **opts)
    return predict_tiled(fn, rgb, plan)


def tiled_torch_call(model, rgb: np.ndarray) -> np.ndarray:
    """``model.network`` (torch, eval mode) on ``rgb (H, W, 3)`` → ``(H, W, B)``, tiled when large.

    The probe measures the network's memory per pixel, its receptive-field
    radius (the margin: tiles then agree with whole-image inference wherever
    the network is local) and its pooling grid.
    """
    import torch

    def run(x: np.ndarray) -> np.ndarray:
        t = torch.from_numpy(np.ascontiguousarray(x.transpose(2, 0, 1))[None]).to(model.device)
        with torch.no_grad():
            return model.network(t)[0].permute(1, 2, 0).cpu().numpy()

    def margin() -> int:
        with torch.enable_grad():
            m = torch_receptive_radius(model.network, align=torch_align(model.network))
        model.network.zero_grad(set_to_none=True)
        return m

    net = model.network
    cap = getattr(net, "max_tile_pixels", None)

    def bytes_per_pixel() -> float:
        bpp = torch_bytes_per_pixel(net)
        if cap is not None:
            # memory super-linear in the tile (global attention): the network says how
            # large a tile fits the budget; the per-pixel figure is raised to match
            budget = env_max_bytes() or int(min(DEFAULT_MAX_BYTES,
                                                AVAILABLE_SHARE * available_memory()))
            bpp = max(bpp, budget / cap(budget))
        return bpp

    fixed_margin = getattr(net, "TILING_MARGIN", None)
    return tiled_network_call(model, run, rgb, {
        "bytes_per_pixel": bytes_per_pixel,
        "margin": (lambda: int(fixed_margin)) if fixed_margin is not None else margin,
        "align": lambda: torch_align(net)})


#: ONNX graphs cannot be introspected here: a margin and grid that cover the
#: small and tiny mehs networks (radius 54 and 15 px, 3 and 2 poolings) and
#: most U-Nets up to 5 poolings; set ``model.tiling = {"margin": ...}`` otherwise.
ONNX_DEFAULT_MARGIN, ONNX_DEFAULT_ALIGN = 64, 32


def tiled_onnx_call(model, fn: Callable[[np.ndarray], np.ndarray], rgb: np.ndarray) -> np.ndarray:
    """An ONNX model's whole-image ``fn`` on ``rgb``, tiled when large.

    Memory per pixel is measured once: the growth of the process's resident
    memory over a 256×256 probe run (onnxruntime's arena keeps its peak), with
    a floor of 1 kB per pixel in case the arena was already grown by earlier calls.
    """
    def memory() -> float:
        n = 256
        before = _rss()
        fn(np.zeros((n, n, 3), dtype=np.float32))
        return max(1024.0, 1.25 * max(0, _rss() - before) / n ** 2)

    return tiled_network_call(model, fn, rgb, {
        "bytes_per_pixel": memory, "margin": lambda: ONNX_DEFAULT_MARGIN,
        "align": lambda: ONNX_DEFAULT_ALIGN})


def _rss() -> int:
    try:
        import psutil

        return int(psutil.Process().memory_info().rss)
    except ImportError:
        with open("/proc/self/statm") as f:
            return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE")
