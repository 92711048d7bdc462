"""The down-sampling grid of a network, read off the shapes its operators produce.

Tiles equal whole-image inference only where their edges lie on the network's grid: a
network that pools ``d`` times by 2 is equivariant to shifts by multiples of ``2**d``
and to no others (a shift by 8 moves a 5-level U-Net's deepest cells by a quarter of a
cell). mehs's own networks declare their pooling ``depth``; a user's network declares
nothing, and until session 26 it was given a grid of 8 — a 5-level U-Net, or a network
that pools in cells of 32 through ``torch.nn.functional`` alone, was tiled off its grid
and its output was a tenth of its range off near the seams, silently.

The network runs on three small random inputs, :data:`SHAPES`: ``H × W``, its transpose,
and half its size. Every operator's output shapes are recorded (torch:
:func:`torch_strides`, a ``TorchDispatchMode``, which sees functional poolings,
``pixel_unshuffle``, ``unfold``, strided convolutions and the operators inside a traced or
scripted module alike; ONNX: onnxruntime's profiler, :mod:`mehs.ssr.tiling_onnx_probes`), and
each output is compared with the same output of the other runs (:func:`map_strides`,
:func:`flattened_strides`):

- two dimensions that follow the input's height and width, each down-sampled by some
  stride (``(H/2, W/16)``: an anisotropic pooling gives both 2 and 16; ``(C, H/16, 16,
  W/16, 16)``: blocks through a view) — a map;
- one dimension that follows the input's area down-sampled by ``s²`` — windows or tokens
  flattened (``unfold`` into 16×16 windows, a Swin block's window count).

A weight or an attention matrix that happens to have such a shape does not follow the
input and is no map. The grid is the least common multiple of the strides found: shifts
by it move every down-sampled map by whole cells.

A forward-mode or gradient measurement of the period was tried in session 25 and
reverted: a weak pooled path diluted below any tolerance read as no period, and a path
gated on brightness was closed on the probe's input. The shapes an operator produces do
not depend on the weights or on the input's values.

What the shapes cannot show: a down-sampling inside one fused operator that returns a
full-size map (none in ``torch.nn``); declare ``tiling={"align": …}`` for such a network.
"""

from __future__ import annotations

import math
from collections import defaultdict

#: The probes' input sizes: ``(384, 256)``, its transpose (which hold every power-of-two
#: stride up to 128 exactly; others, 3, 24, a padded 48, are read from rounded sizes)
#: and half its size (flattened maps, whose length follows the area).
PROBE_SHAPE = (384, 256)

#: Strides above this are not taken as a grid (a map of 2×3 cells of a 384×256 probe).
MAX_STRIDE = 256


def shapes(base: tuple[int, int] = PROBE_SHAPE) -> tuple[tuple[int, int], ...]:
    """The three probe sizes for ``base`` (see module doc)."""
    h, w = base
    return (h, w), (w, h), (max(1, h // 2), max(1, w // 2))


def _pick(fits: list[int], exact: list[int]) -> int | None:
    """The one stride among ``fits``: the exact one, else the only one; None if ambiguous."""
    if len(fits) == 1:
        return fits[0]
    return exact[0] if len(exact) == 1 else None


def _axis_stride(d1: int, n1: int, d2: int, n2: int) -> int | None:
    """The stride ``s ≥ 1`` with ``d ≈ n / s`` in both runs (each the exact quotient or
    rounded either way: a network pads or crops to its multiple); None when the size
    does not follow the input (``d1 == d2``), or no stride or several fit."""
    if d1 == d2 or d1 < 1 or d2 < 1 or d1 > n1 or d2 > n2:
        return None
    lo = max(1, n1 // (d1 + 1))
    hi = min(MAX_STRIDE, n1 // (d1 - 1) + 1 if d1 > 1 else MAX_STRIDE)
    fits = [s for s in range(lo, hi + 1)
            if d1 in (n1 // s, -(-n1 // s)) and d2 in (n2 // s, -(-n2 // s))]
    return _pick(fits, [s for s in fits if n1 == d1 * s and n2 == d2 * s]
                 or [s for s in fits if n1 == d1 * s or n2 == d2 * s])


def _area_stride(l1: int, size1: tuple[int, int], l2: int, size2: tuple[int, int]) -> int | None:
    """The stride ``s ≥ 2`` whose cells of ``size1`` and ``size2`` number ``l1`` and ``l2``
    (each side rounded either way); None when none or several fit."""
    if l1 == l2:
        return None

    def counts(size, s):
        (h, w) = size
        return {a * b for a in (h // s, -(-h // s)) for b in (w // s, -(-w // s))}

    fits = [s for s in range(2, MAX_STRIDE + 1)
            if l1 in counts(size1, s) and l2 in counts(size2, s)]
    return _pick(fits, [s for s in fits if l1 * s * s == size1[0] * size1[1]
                        and l2 * s * s == size2[0] * size2[1]])


def _fits(d: int, n: int, s: int) -> bool:
    return d in (n // s, -(-n // s))


def map_strides(sa: tuple[int, ...], sb: tuple[int, ...] | None, sc: tuple[int, ...] | None,
                sizes: tuple[tuple[int, int], ...]) -> set[int]:
    """Strides ``≥ 2`` of the maps one operator output shows, shaped ``sa``, ``sb``, ``sc``
    on the inputs of :func:`shapes` ``sizes`` (None: not seen in that run).

    Two dimensions (the only two that differ) are a map when each follows its input
    axis between the first two runs with a stride of its own; strides that differ between the axes must
    hold in the third run too (rows that a memory-lean network processes in strips of
    so many pixels follow the width inversely, and read as a stride of 3 otherwise).
    """
    if sb is None or len(sa) != len(sb) or sa == sb:
        return set()
    diff = [k for k in range(len(sa)) if sa[k] != sb[k]]
    if len(diff) != 2:
        return set()
    (ha, wa), (hb, wb), (hc, wc) = sizes
    found: set[int] = set()
    # the two axes need not be adjacent ((C, H/16, 16, W/16, 16): 16×16 blocks through a
    # view), nor in the input's order
    for j, k in (diff, diff[::-1]):
        sh = _axis_stride(sa[j], ha, sb[j], hb)
        sw = _axis_stride(sa[k], wa, sb[k], wb)
        if sh is None or sw is None:
            continue
        if sh != sw:
            ok = (sc is not None and len(sc) == len(sa)
                  and all(sc[m] == sa[m] for m in range(len(sa)) if m not in (j, k))
                  and _fits(sc[j], hc, sh) and _fits(sc[k], wc, sw))
            if not ok:
                continue
        found |= {sh, sw} - {1}
    return found


def flattened_strides(sa: tuple[int, ...], sb: tuple[int, ...] | None,
                      sc: tuple[int, ...] | None, sizes: tuple[tuple[int, int], ...]) -> set[int]:
    """The stride ``≥ 2`` of a dimension that counts cells of the input's area (windows or
    tokens flattened): the same on the first two sizes (one area), ``s²`` times fewer
    than the pixels on the first and the third."""
    if sb != sa or sc is None or len(sc) != len(sa):
        return set()
    diff = [k for k in range(len(sa)) if sa[k] != sc[k]]
    if len(diff) != 1:
        return set()
    s = _area_stride(sa[diff[0]], sizes[0], sc[diff[0]], sizes[2])
    return set() if s is None else {s}


def strides_of_runs(runs: list[dict], sizes: tuple[tuple[int, int], ...]) -> set[int]:
    """Strides from the recorded outputs of the runs on :func:`shapes` ``sizes``: each
    run a dict from an output's identity (an ONNX value's name; the i-th output of the
    k-th call of a torch operator) to its shape (:func:`map_strides`,
    :func:`flattened_strides`)."""
    found: set[int] = set()
    first, second, third = runs
    for key, sa in first.items():
        sb, sc = second.get(key), third.get(key)
        found |= map_strides(sa, sb, sc, sizes) | flattened_strides(sa, sb, sc, sizes)
    return found


def probe_shape(max_pixels: int | None = None, multiple: int = 1) -> tuple[int, int]:
    """:data:`PROBE_SHAPE`, halved until it has at most ``max_pixels`` (the cap of a network
    whose memory grows faster than its input) but not below 192×128: on smaller sizes a
    network that pads itself to a grid of 64 distorts every map, and the strides read off
    them were wrong (13 and 24 at 96×64); its sides rounded up to ``multiple`` (and kept
    unequal, and even)."""
    h, w = PROBE_SHAPE
    if max_pixels is not None:
        while h * w > max_pixels and w > 128:
            h, w = h // 2, w // 2
    k = max(1, int(multiple))
    k2 = k if k % 2 == 0 else 2 * k
    h, w = -(-h // k2) * k2, -(-w // k2) * k2
    return (h + k2, w) if h == w else (h, w)


def torch_strides(network, *, shape: tuple[int, int] = PROBE_SHAPE, device=None,
                  dtype=None) -> set[int]:
    """Strides ``s ≥ 2`` of the down-sampled maps ``network`` computes (see module doc).

    ``network`` maps ``(1, 3, H, W)`` to anything; it runs three times, without autograd,
    on :func:`shapes` ``(shape)`` (inputs from a private seeded generator: the caller's
    random state is left alone).
    """
    import torch
    from torch.utils._python_dispatch import TorchDispatchMode
    from torch.utils._pytree import tree_flatten

    h, w = (int(v) for v in shape)
    if h == w:
        raise ValueError(f"the grid probe needs a non-square shape, got {h}×{w}")

    class Shapes(TorchDispatchMode):
        def __init__(self):
            super().__init__()
            self.seen: dict[tuple[str, int, int], tuple[int, ...]] = {}
            self.calls: dict[str, int] = defaultdict(int)

        def __torch_dispatch__(self, func, types, args=(), kwargs=None):
            out = func(*args, **(kwargs or {}))
            name = str(func.overloadpacket)
            k = self.calls[name]
            self.calls[name] += 1
            for i, t in enumerate(tree_flatten(out)[0]):
                if isinstance(t, torch.Tensor) and t.ndim >= 1:
                    self.seen[(name, k, i)] = tuple(t.shape)
            return out

    if device is None or dtype is None:
        param = next(iter(network.parameters()), None)
        device = device or (param.device if param is not None else "cpu")
        dtype = dtype or (param.dtype if param is not None and param.is_floating_point()
                          else torch.float32)
    g = torch.Generator(device=device)
    g.manual_seed(0x6D656873)
    sizes = shapes((h, w))
    runs = []
    for size in sizes:
        x = torch.rand(1, 3, *size, generator=g, device=device).to(dtype)
        mode = Shapes()
        with torch.no_grad(), mode:
            network(x)
        runs.append(mode.seen)
        del x
    return strides_of_runs(runs, sizes)


def torch_grid(network, *, max_pixels: int | None = None, multiple: int = 1) -> int:
    """The least common multiple of :func:`torch_strides` (1 where nothing down-samples).

    ``max_pixels``: the most pixels one probe may have (a network whose memory grows
    faster than its input, AWAN's non-local attention): see :func:`probe_shape`.
    ``multiple``: the sizes the network takes (:mod:`mehs.ssr.tiling_pad`); the probe's
    sides are made multiples of it, so that no padding blurs the maps' sizes.
    """
    found = torch_strides(network, shape=probe_shape(max_pixels, multiple))
    return math.lcm(*found) if found else 1
