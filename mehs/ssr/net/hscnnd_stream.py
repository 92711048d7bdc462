"""HSCNN-D inference streamed down the image's rows (issue 16).

HSCNN-D's dense features grow to ``4·head + n·fuse`` channels (1088 in the full
preset: 9.1 GB for a 2048×1024 image in one piece), and its 31-pixel receptive
field makes tiles recompute wide overlaps. Each of its layers looks only one row
up and down, so the image can be swept top to bottom as a wavefront: feature
``k`` (``0`` the head, ``k`` the ``k``-th dense block) runs ``n − k`` rows ahead of
the output, every feature row is computed once, and only a window of
``B + n + 1`` rows of all channels is alive (``B`` output rows per step; 0.56 GB
for the full preset at width 2048, where the dense features took 9.1 GB). The products are the whole image's; the
memory grows with the width, not the height.

Step ``t`` computes feature ``k`` up to row ``min(H, t·B + n − k)`` and the output
up to ``min(H, t·B)``: block ``k`` reads rows ``[e − 1, e' + 1)`` of the features
before it, which earlier blocks of the same step have already reached, and the
output reads rows every feature has. The window then keeps the ``n + 1`` rows
the next step reads again.

Layer by layer as :class:`~mehs.ssr.net.hscnnd2018.HSCNND2018` (plain modules only:
a subclass, a hook or a replaced part runs the dense graph). The 1×1 convolutions
are matrix products on the window's channel-major rows, read in place (a
convolution would first copy the up to 1056 channels it reads).

Shapes are PyTorch's ``(N, C, H, W)``; inference only.
"""

from __future__ import annotations

import torch
from torch import nn
import torch.nn.functional as F

from mehs.ssr.net.strips import _plain


def streamable(net: nn.Module) -> bool:
    """Whether ``net`` is exactly an HSCNN-D of plain parts (see the module's doc)."""
    from mehs.ssr.net.hscnnd2018 import (BLOCK_CONVS, HSCNND2018, DenseFusionBlock,
                                         _strippable, plain_conv)

    if not _plain(net, HSCNND2018) or type(net.relu) is not nn.ReLU:
        return False
    # (the convolutions are called by their weights: a grouped one put in place of one,
    # which the dense path's strips would run by its module, is not streamed)
    for b in net.blocks:
        if not (isinstance(b, DenseFusionBlock) and _strippable(b)
                and all(getattr(b, name).groups == 1 for name in BLOCK_CONVS)):
            return False
    convs = ((net.up1, 3), (net.down1, 3), (net.up2, 1), (net.down2, 1), (net.conv_out, 1))
    return all(plain_conv(c, k) and c.groups == 1 for c, k in convs)


#: Least output rows per step: the compressed maps' two context rows, computed again
#: by each step, then cost at most 1/16 more of the blocks' compressions.
MIN_STEP_ROWS = 32


def step_rows(net: nn.Module) -> int:
    """Output rows ``B`` per step: ``max(n + 2, MIN_STEP_ROWS)`` (0: do not stream).

    Not a function of the width: a step's memory, the window's included, is then
    a fixed number of rows of the image's width, which the memory probe measures
    (:func:`mehs.ssr.tiling_probes.torch_memory_probe`). ``net.chunk_pixels = 0``
    (whole maps) turns streaming off. At least ``n + 2`` rows, so that the ``n + 1``
    rows kept between steps are a minority of the window.
    """
    if net.chunk_pixels <= 0:
        return 0
    return max(len(net.blocks) + 2, MIN_STEP_ROWS)


def window_rows(net: nn.Module) -> int:
    """Rows of all feature channels alive at once: ``B + n + 1`` (0: not streamed)."""
    b = step_rows(net)
    return b + len(net.blocks) + 1 if b else 0


def wanted(net: nn.Module, x: torch.Tensor) -> bool:
    """Whether ``net`` streams ``x`` (any plain HSCNN-D with strips on: an image no taller
    than the window holds the dense features, in steps whose temporaries are bounded)."""
    return bool(window_rows(net)) and x.numel() > 0 and streamable(net)


def forward(net: nn.Module, x: torch.Tensor) -> torch.Tensor:
    """``net.body(x)`` for a plain HSCNN-D (:func:`streamable`), streamed; ``x`` ``(N, 3, H, W)``."""
    n, _, h, w = x.shape
    out = x.new_empty(n, net.conv_out.out_channels, h, w)
    for i in range(n):
        _one(net, x[i:i + 1], out[i], step_rows(net))
    return out


def _one(net, x: torch.Tensor, out: torch.Tensor, step: int) -> None:
    _, _, h, w = x.shape
    nb = len(net.blocks)
    offsets = [0, net.c0]
    for b in net.blocks:
        offsets.append(offsets[-1] + b.fusion.out_channels)
    # (a step reads rows [base, end[0]): never more than the window, nor than the image)
    buf = x.new_empty(offsets[-1], min(h, step + nb + 1), w)
    done = [0] * (nb + 1)                        # rows of each feature computed so far
    base = 0                                     # the image row of the window's row 0
    o = 0                                        # output rows written
    t = 0
    while o < h:
        new_base = max(0, o - 1)
        if new_base > base:
            keep = done[0] - new_base            # (feature 0 is the furthest ahead)
            _shift(buf, new_base - base, keep)
            base = new_base
        end = [min(h, t * step + nb - k) for k in range(nb + 1)]
        if end[0] > done[0]:
            _head(net, x, buf[:net.c0], done[0], end[0], base)
        for k, block in enumerate(net.blocks, start=1):
            if end[k] > done[k]:
                _block(block, buf, offsets[k], done[k], end[k], base, h)
        for k in range(nb + 1):
            done[k] = max(done[k], end[k])
        o_end = min(h, t * step)
        if o_end > o:
            rows = buf[:, o - base:o_end - base].reshape(offsets[-1], -1)
            y = _linear(net.conv_out, rows)
            out[:, o:o_end] = y.view(-1, o_end - o, w)
            o = o_end
        t += 1


def _shift(buf: torch.Tensor, s: int, count: int) -> None:
    # rows [s, s + count) to [0, count) in pieces of at most s rows, low ones first:
    # no piece overlaps itself, and none overwrites rows a later piece still reads
    for i in range(0, count, s):
        m = min(s, count - i)
        buf[:, i:i + m] = buf[:, s + i:s + i + m]


def _linear(conv: nn.Conv2d, rows: torch.Tensor) -> torch.Tensor:
    """A 1×1 convolution of ``rows`` ``(C_in, P)`` (strided channels, contiguous pixels)
    → ``(C_out, P)``: one matrix product reading the window in place."""
    wt = conv.weight.view(conv.out_channels, conv.in_channels)
    if conv.bias is None:
        return torch.mm(wt, rows)
    return torch.addmm(conv.bias.unsqueeze(1), wt, rows)


def _rows2d(t: torch.Tensor) -> torch.Tensor:
    # (C, r, W) -> (C, r·W); a view for the window's slices (rows of one channel adjacent)
    return t.reshape(t.shape[0], -1)


def _conv3(conv: nn.Conv2d, f: torch.Tensor, top: int, bottom: int) -> torch.Tensor:
    """A zero-padded 3×3 ``conv`` of ``f`` ``(C, r, W)`` whose first and last rows are
    context; ``top``/``bottom``: zero rows to add where the context lies beyond the image."""
    part = f.unsqueeze(0)
    if top or bottom:
        part = F.pad(part, (0, 0, top, bottom))
    return F.conv2d(part, conv.weight, conv.bias, 1, (0, 1))[0]


def _head(net, x: torch.Tensor, dst: torch.Tensor, a: int, b: int, base: int) -> None:
    h, w = x.shape[2], x.shape[3]
    lo, hi = max(0, a - 1), min(h, b + 1)
    top, bottom = lo - (a - 1), (b + 1) - hi
    part = x[0, :, lo:hi]
    head = net.up2.in_channels
    c = 0
    for first, second in ((net.up1, net.up2), (net.down1, net.down2)):
        u = _conv3(first, part, top, bottom).relu_()
        v = _linear(second, _rows2d(u)).relu_()
        dst[c:c + head, a - base:b - base] = u
        dst[c + head:c + head + second.out_channels, a - base:b - base] = v.view(-1, b - a, w)
        c += head + second.out_channels


def _block(block, buf: torch.Tensor, c: int, a: int, b: int, base: int, h: int) -> None:
    """Rows ``a:b`` of a dense fusion block's new channels into ``buf[c:c + fuse]``, from
    the channels before them (rows ``a − 1 : b + 1``, zero beyond the image)."""
    w = buf.shape[2]
    lo, hi = max(0, a - 1), min(h, b + 1)
    src = buf[:c, lo - base:hi - base]
    f = _linear(block.conv1, _rows2d(src)).relu_().view(-1, hi - lo, w)
    top, bottom = lo - (a - 1), (b + 1) - hi
    u1 = _conv3(block.up1, f, top, bottom).relu_()
    d1 = _conv3(block.down1, f, top, bottom).relu_()
    del f
    u2 = _linear(block.up2, _rows2d(u1)).relu_()
    d2 = _linear(block.down2, _rows2d(d1)).relu_()
    cat = torch.cat([_rows2d(u1), u2, _rows2d(d1), d2])
    del u1, u2, d1, d2
    y = _linear(block.fusion, cat).relu_()
    buf[c:c + block.fusion.out_channels, a - base:b - base] = y.view(-1, b - a, w)
