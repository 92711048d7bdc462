"""The down-sampling grid of a torch network, read off the shapes its operators produce.

Tiles equal whole-image inference only where their edges lie on the network's grid: a
network that pools ``d`` times by 2 is equivariant to shifts by multiples of ``2**d``
and to no others (a shift by 8 moves a 5-level U-Net's deepest cells by a quarter of a
cell). mehs's own networks declare their pooling ``depth``; a user's network declares
nothing, and until session 26 it was given a grid of 8 — a 5-level U-Net, or a network
that pools in cells of 32 through ``torch.nn.functional`` alone, was tiled off its grid
and its output was a tenth of its range off near the seams, silently.

:func:`torch_strides` runs the network twice on small random inputs, ``H × W`` and its
transpose ``W × H``, under a ``TorchDispatchMode`` that sees every operator's output —
functional poolings, ``pixel_unshuffle``, strided convolutions, the operators inside a
traced or scripted module alike — and takes as a down-sampled map every output whose two
adjacent dimensions are ``(≈H/s, ≈W/s)`` in the first run and ``(≈W/s, ≈H/s)`` at the same
operator in the second (so a weight or an attention matrix that happens to have such a
shape, which does not follow the input's, is not one). The grid is the least common
multiple of those strides: shifts by it move every down-sampled map by whole cells.

A forward-mode or gradient measurement of the period was tried in session 25 and
reverted: a weak pooled path diluted below any tolerance read as no period, and a path
gated on brightness was closed on the probe's input. The shapes an operator produces do
not depend on the weights or on the input's values.

What the shapes cannot show: a down-sampling inside one fused operator that returns a
full-size map (none in ``torch.nn``), and windowed attention over tokens whose window
tensors do not keep the image's two axes adjacent (declare ``tiling={"align": …}``).
"""

from __future__ import annotations

import math

#: Probe sizes: ``(384, 256)`` and its transpose hold every power-of-two stride up to
#: 128 exactly; other strides (3, 24, a padded 48) are read from rounded sizes.
PROBE_SHAPE = (384, 256)

#: Strides above this are not taken as a grid (a map of 2×3 cells of a 384×256 probe).
MAX_STRIDE = 256


def _stride_of(d: int, e: int, h: int, w: int) -> int | None:
    """The stride ``s ≥ 2`` whose map of an ``h × w`` input is ``d × e`` (each side the
    exact quotient, or rounded either way: a network pads or crops to its multiple);
    None when no stride gives that shape, or several do and none exactly."""
    if d < 1 or e < 1 or d >= h or e >= w or d == e:
        # full size or up-sampled; or square, which a map of a non-square input is
        # only when it is a global statistic's 1×1 (or a chance shape that does not
        # follow the input, which the transposed run would reject anyway)
        return None
    fits = []
    # s with d ∈ {⌊h/s⌋, ⌈h/s⌉}: h/(d+1) < s < h/(d-1)
    lo = max(2, h // (d + 1))
    hi = min(MAX_STRIDE, h // (d - 1) + 1 if d > 1 else MAX_STRIDE)
    for s in range(lo, hi + 1):
        if d in (h // s, -(-h // s)) and e in (w // s, -(-w // s)):
            fits.append(s)
    if len(fits) <= 1:
        return fits[0] if fits else None
    exact = [s for s in fits if h == d * s and w == e * s]
    if len(exact) == 1:
        return exact[0]
    one_axis = [s for s in fits if h == d * s or w == e * s]
    return one_axis[0] if len(one_axis) == 1 else None


def _adjacent_pairs(shape: tuple[int, ...]):
    for j in range(len(shape) - 1):
        yield j, shape[j], shape[j + 1]


def torch_strides(network, *, shape: tuple[int, int] = PROBE_SHAPE, device=None,
                  dtype=None) -> set[int]:
    """Strides ``s ≥ 2`` of the down-sampled maps ``network`` computes (see module doc).

    ``network`` maps ``(1, 3, H, W)`` to anything; it runs twice, without autograd, on
    ``shape`` and its transpose (inputs from a private seeded generator: the caller's
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
            self.seen: set[tuple[str, tuple[int, ...]]] = set()

        def __torch_dispatch__(self, func, types, args=(), kwargs=None):
            out = func(*args, **(kwargs or {}))
            for t in tree_flatten(out)[0]:
                if isinstance(t, torch.Tensor) and t.ndim >= 2:
                    self.seen.add((str(func.overloadpacket), tuple(t.shape)))
            return out

    if device is None or dtype is None:
        param = next(iter(network.parameters()), None)
        device = device or (param.device if param is not None else "cpu")
        dtype = dtype or (param.dtype if param is not None and param.is_floating_point()
                          else torch.float32)
    g = torch.Generator(device=device)
    g.manual_seed(0x6D656873)
    runs = []
    for size in ((h, w), (w, h)):
        x = torch.rand(1, 3, *size, generator=g, device=device).to(dtype)
        mode = Shapes()
        with torch.no_grad(), mode:
            network(x)
        runs.append(mode.seen)
        del x
    first, second = runs
    strides = set()
    for op, out in first:
        for j, d, e in _adjacent_pairs(out):
            s = _stride_of(d, e, h, w)
            if s is None:
                continue
            # the same operator's map of the transposed input, with its other dims unchanged
            if (op, out[:j] + (e, d) + out[j + 2:]) in second:
                strides.add(s)
    return strides


def probe_shape(max_pixels: int | None = None, multiple: int = 1) -> tuple[int, int]:
    """:data:`PROBE_SHAPE`, halved until it has at most ``max_pixels``, its sides rounded up
    to ``multiple`` (and kept unequal)."""
    h, w = PROBE_SHAPE
    if max_pixels is not None:
        while h * w > max_pixels and w > 16:
            h, w = h // 2, w // 2
    k = max(1, int(multiple))
    h, w = -(-h // k) * k, -(-w // k) * k
    return (h + k, w) if h == w else (h, w)


def torch_grid(network, *, max_pixels: int | None = None, multiple: int = 1) -> int:
    """The least common multiple of :func:`torch_strides` (1 where nothing down-samples).

    ``max_pixels``: the most pixels one probe may have (a network whose memory grows
    faster than its input, AWAN's non-local attention); the probe shrinks by powers of
    two to fit, and then reads strides up to ``128 × scale`` exactly. ``multiple``: the
    sizes the network takes (:mod:`mehs.ssr.tiling_pad`); the probe's sides are made
    multiples of it, so that no padding blurs the maps' sizes.
    """
    found = torch_strides(network, shape=probe_shape(max_pixels, multiple))
    return math.lcm(*found) if found else 1
