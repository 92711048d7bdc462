"""Networks that take only sizes divisible by some ``k``: pad to the multiple, crop back.

A network that down-samples ``d`` times (a U-Net, an HSCNN+-like encoder, the
paper's variants without internal padding) needs ``H`` and ``W`` to be multiples
of ``k = 2**d``: on other sizes it raises, or its up-sampled skip connections are
off by a pixel. Each call of such a model here (a whole image, every tile of
:mod:`mehs.ssr.tiling`, every probe) gets its input reflect-padded at the bottom and
right to the next multiple of ``k``, and its output cropped back to the input's size.

Tiles then agree with whole-image inference of the padded image (cropped): inner tiles
are multiples of the tiling grid, which is made a multiple of ``k``, and need no
padding; an image's last tile along an axis ends at the image's edge, so its reflected
rows and columns are the image's own as long as the tile is at least ``k`` pixels long
(``np.pad`` reflects a shorter one within itself). An axis's last tile is longer than
the tiles' overlap (``2 margin + blend``), and :func:`mehs.ssr.tiling.tiled_network_call`
raises the margin where the overlap would be under ``k − 1`` (with the tiles on the grid
only tiles that do not overlap at all, margin and blend 0, could leave a shorter one).

Image-wide pooling means (:mod:`mehs.ssr.tiling_global`, :mod:`mehs.ssr.tiling_onnx`)
size a last tile's pooled-map cells on its padded length: a 42-pixel tile padded to 48
pools to 6 cells of 8 pixels.

Where ``k`` comes from (:func:`size_multiple`): ``model.tiling["size_multiple"]`` (the
user's option), else the model's ``size_multiple`` attribute, which torch networks
(an attribute of the network), mehs's ONNX export (metadata ``mehs_size_multiple``) and
``OnnxModel(size_multiple=...)`` set; default 1 (any size).
"""

from __future__ import annotations

import math
from typing import Any, Callable

import numpy as np

from mehs.errors import InputError

#: ONNX metadata property that carries the size multiple of an exported graph.
ONNX_SIZE_MULTIPLE_KEY = "mehs_size_multiple"


def check_multiple(value: Any, what: str = "size multiple") -> int:
    """``value`` as an int ≥ 1, else :class:`InputError` naming ``what``."""
    try:
        k = int(value)
        ok = k == float(value) and k >= 1
    except (TypeError, ValueError, OverflowError):
        ok = False
    if not ok:
        raise InputError(f"{what} must be a whole number ≥ 1, got {value!r}")
    return k


def declared_multiple(given: Any, *owners: Any, what: str = "size_multiple") -> int:
    """``given`` if not None, else the first ``size_multiple`` attribute of ``owners`` that
    is set, else 1; checked by :func:`check_multiple` (``what`` names it in the error)."""
    for v in (given, *(getattr(o, "size_multiple", None) for o in owners)):
        if v is not None:
            return check_multiple(v, what)
    return 1


def size_multiple(model: Any) -> int:
    """The multiple ``model``'s inputs must have: ``model.tiling["size_multiple"]``, else
    ``model.size_multiple``, else 1."""
    t = getattr(model, "tiling", None)
    if isinstance(t, dict) and t.get("size_multiple") is not None:
        return check_multiple(t["size_multiple"], "tiling option size_multiple")
    v = getattr(model, "size_multiple", None)
    return 1 if v is None else check_multiple(v, f"{getattr(model, 'name', 'model')}: "
                                                 "size_multiple")


def grid(align: int, k: int) -> int:
    """A tiling grid that is a multiple of both ``align`` and ``k`` (their lcm)."""
    return math.lcm(int(align), int(k))


def pad_amounts(h: int, w: int, k: int) -> tuple[int, int]:
    """Rows and columns to add at the bottom and right for multiples of ``k``."""
    return (-h) % k, (-w) % k


def pad_to_multiple(x: np.ndarray, k: int) -> np.ndarray:
    """``(H, W, C)`` → ``(H', W', C)`` with H', W' the next multiples of ``k``, reflect-padded
    at the bottom and right (``x`` itself when nothing is needed)."""
    ph, pw = pad_amounts(x.shape[0], x.shape[1], k)
    if not (ph or pw):
        return x
    # numpy reflects repeatedly where the pad exceeds the axis (a 1-pixel image repeats)
    return np.pad(x, ((0, ph), (0, pw), (0, 0)), mode="reflect")


def call_padded(fn: Callable[[np.ndarray], np.ndarray], rgb: np.ndarray, k: int,
                name: str = "model") -> np.ndarray:
    """``fn`` on ``rgb (H, W, 3)`` padded to multiples of ``k``, its ``(H', W', B)`` output
    cropped to ``(H, W, B)`` (a view: the layout of ``fn``'s output is kept)."""
    h, w = rgb.shape[:2]
    if k <= 1 or not any(pad_amounts(h, w, k)):
        return fn(rgb)
    x = pad_to_multiple(rgb, k)
    y = np.asarray(fn(x))
    if y.ndim != 3 or y.shape[:2] != x.shape[:2]:
        raise InputError(f"{name}: a {x.shape[0]}×{x.shape[1]} input (a {h}×{w} image padded "
                         f"to multiples of {k}) gave output shape {y.shape}, not "
                         f"({x.shape[0]}, {x.shape[1]}, bands)")
    return y[:h, :w]


def padded(fn: Callable[[np.ndarray], np.ndarray], k: int,
           name: str = "model") -> Callable[[np.ndarray], np.ndarray]:
    """``fn`` wrapped by :func:`call_padded` (``fn`` itself for ``k = 1``)."""
    if k <= 1:
        return fn
    return lambda rgb: call_padded(fn, rgb, k, name)


def padded_torch_module(network, k: int):
    """A torch module running ``network`` on ``(N, C, H, W)`` reflect-padded to multiples of
    ``k`` and cropped back (``network`` itself for ``k = 1``): for the tiling probes, which
    run the network on sizes of their own. ``network``'s modules are its submodules."""
    if k <= 1:
        return network
    import torch
    import torch.nn.functional as F

    class _Padded(torch.nn.Module):
        def __init__(self, net):
            super().__init__()
            self.network = net

        def forward(self, x):
            h, w = int(x.shape[-2]), int(x.shape[-1])
            ph, pw = pad_amounts(h, w, k)
            if ph or pw:
                # torch's reflect needs the pad below the size: replicate the rest
                mode = "reflect" if ph < h and pw < w else "replicate"
                x = F.pad(x, (0, pw, 0, ph), mode=mode)
            return self.network(x)[..., :h, :w]

    return _Padded(network)
