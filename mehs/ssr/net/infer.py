"""Inference on large images: whole, or in overlapping tiles for purely local networks.

A network whose output pixel depends only on the ``R = receptive_radius`` pixels
around it (HSCNN-D) gives *exactly* the whole-image result when the image is cut
into tiles that overlap by ``R`` on every side and only the tile centres are kept;
memory then grows with the tile, not the image (HSCNN-D's 1088 dense feature channels
took ~9 GB for a 2048×1024 image in one piece; its inference now streams the rows and
holds a window of them, :mod:`mehs.ssr.net.hscnnd_stream`). Networks with image-wide
operations (attention over all pixels, global pooling, pooling pyramids) have
``receptive_radius = None`` and are run whole unless the caller asks for
``approximate=True`` (plain tiles without overlap: each tile is then treated as an
image of its own, e.g. AWAN's non-local block, whose pixel-by-pixel affinity would
have 2.7·10¹¹ entries per quadrant of a 2048×1024 image).
"""

from __future__ import annotations

import torch

from mehs.ssr.net.base import SSRNetwork


@torch.no_grad()
def predict_tiled(network: SSRNetwork, rgb: torch.Tensor, tile: int = 512,
                  spectra: bool = True, approximate: bool = False) -> torch.Tensor:
    """``rgb`` ``(N, 3, H, W)`` → ``(N, L, H, W)``, in ``tile``×``tile`` pieces when exact.

    Parameters
    ----------
    network
        A zoo network (eval mode is the caller's business).
    rgb
        Linear RGB.
    tile
        Side of the kept centre of each tile (the tile itself is ``tile + 2R``).
    spectra
        True: :meth:`SSRNetwork.spectra` (luminance restored in similarity mode);
        False: the raw output.
    approximate
        Also tile networks with image-wide operations (no overlap; not exact).
    """
    if tile < 1:
        raise ValueError(f"tile must be at least 1 pixel, got {tile}")
    fn = network.spectra if spectra else network
    r = network.receptive_radius
    if r is None and approximate:
        r = 0
    h, w = rgb.shape[-2:]
    if r is None or (h <= tile and w <= tile):
        return fn(rgb)
    out = None
    for y0 in range(0, h, tile):
        for x0 in range(0, w, tile):
            y1, x1 = min(y0 + tile, h), min(x0 + tile, w)
            ya, xa = max(0, y0 - r), max(0, x0 - r)
            yb, xb = min(h, y1 + r), min(w, x1 + r)
            piece = fn(rgb[..., ya:yb, xa:xb])
            if out is None:
                out = rgb.new_empty(rgb.shape[0], piece.shape[1], h, w)
            out[..., y0:y1, x0:x1] = piece[..., y0 - ya:y1 - ya, x0 - xa:x1 - xa]
    return out
