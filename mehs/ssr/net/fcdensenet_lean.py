"""FC-DenseNet features for a per-pixel head at inference, without the full-resolution
concatenation (issue 16).

The last dense block's map ``[up-sampled, skip = [first conv, level-0 layers], new layers]``
was one full-resolution buffer (192 channels, 1.61 GB for FC-DenseNet56 at 2048×1024), and
at its allocation the level-0 skip was alive beside it: 288 channels. Here the first
convolution (3 input channels: cheaper to recompute for each strip than to hold) is
computed for the rows each consumer reads, and every other group is stored once, where
it is made: the level-0 layers' outputs, the up-sampling's and the last block's own.
Consumers read them a row strip at a time (:class:`~mehs.ssr.net.strips.RowGroups`):
the dense layers and the level-0 transition normalise each group straight into one
strip, and the head (per pixel) reads strips and writes its result into the
up-sampling's memory, rows it has already read.

Each output pixel gets the same products as the plain graph: batch norm runs torch's own
kernel on each group, and only convolutions on strips of other shapes may sum in another
order (equal to float32 rounding; an image of one strip gets the plain graph's numbers
bit for bit).
"""

from __future__ import annotations

import torch
from torch import nn
import torch.nn.functional as F

from mehs.ssr.allocator import trim_heap
from mehs.ssr.net.layers import DenseBlock, DenseLayer, FCDenseNet, TransitionDown
from mehs.ssr.net.strips import (RowGroups, _plain, channel_strip_rows, conv2d_rows,
                                 conv_transpose_into, conv_transpose_shape, training_graph)


def features(net: FCDenseNet, x: torch.Tensor) -> tuple[RowGroups, int, int]:
    """``net``'s features of ``x`` ``(N, 3, h, w)`` as row groups of the padded size,
    and ``(h, w)``: a per-pixel consumer crops its result to them.

    Networks this module cannot run exactly as their forward would (hooks, replaced
    parts, autograd, export) get their forward's tensor as one group.
    """
    h, w = x.shape[-2], x.shape[-1]
    if training_graph() or x.dim() != 4 or not lean(net):
        return RowGroups.of(net(x)), h, w
    m = 2 ** net.depth
    pad_h, pad_w = (-h) % m, (-w) % m
    # (nothing writes into xp: an image on the grid is not copied)
    xp = F.pad(x, (0, pad_w, 0, pad_h), mode="replicate") if pad_h or pad_w else x
    n, _, hp, wp = xp.shape
    first = (net.first.out_channels, lambda a, b: conv2d_rows(net.first, xp, a, b))

    block = net.down_blocks[0]
    level0 = xp.new_empty(n, block.new_channels, hp, wp)
    large = _large(level0)
    skip = RowGroups([first, (block.new_channels, level0)], xp, hp, wp)
    _fill(block, skip)
    y = net.trans_down[0](skip)
    skips = []
    for block, down in zip(net.down_blocks[1:], net.trans_down[1:]):
        y = block(y)
        skips.append(y)
        y = down(y)
    y = net.bottleneck(y)
    for up, block in zip(net.trans_up[:-1], net.up_blocks[:-1]):
        held = [y]
        del y
        if large:
            trim_heap()
        y = net.up_step(up, block, held, skips)

    # the coarser levels' tensors and strips were freed to the C heap, which keeps them
    # resident (0.48 GB of the full paper network's 2.23 GB peak at 2048×1024): returned
    # before the last level's three full-resolution maps are made
    if large:
        trim_heap()
    up, block = net.trans_up[-1], net.up_blocks[-1]
    upsampled = y.new_empty(conv_transpose_shape(up, y))
    conv_transpose_into(up, y, upsampled, net.chunk_pixels)
    del y
    new = xp.new_empty(n, block.new_channels, hp, wp)
    out = RowGroups([(up.out_channels, upsampled), first, (level0.shape[1], level0),
                     (block.new_channels, new)], xp, hp, wp, owned=(upsampled,))
    _fill(block, out, trim=large)
    return out, h, w


#: Bytes of a full-resolution group from which freed heap is returned between stages:
#: ``malloc_trim`` costs milliseconds per call, which small images (tiles, probes) would
#: pay for memory that does not matter at their size.
TRIM_BYTES = 64 << 20


def _large(t: torch.Tensor) -> bool:
    return t.numel() * t.element_size() >= TRIM_BYTES


def _fill(block: DenseBlock, groups: RowGroups, trim: bool = False) -> None:
    """Run ``block``'s layers on ``groups``, whose last group receives the new channels;
    ``trim``: return the freed heap after each layer (its strips' fragments stayed
    resident: 0.1–0.2 GB at FC-DenseNet56's last level at 2048×1024)."""
    new = groups.groups[-1][1]
    c = groups.channels - block.new_channels
    for i, layer in enumerate(block.layers):
        g = block.growth
        layer.run_into(groups.prefix(c + i * g), new[:, i * g:(i + 1) * g])
        if trim:
            trim_heap()


def head(net: FCDenseNet, x: torch.Tensor, channels: int, chunk_pixels: int, strip) -> torch.Tensor:
    """A per-pixel head on ``net``'s features of ``x``: ``strip(part)`` gives the head's
    ``(N, channels, r, w)`` result for features ``part`` ``(N, C, r, w)``, strip by strip
    of about ``chunk_pixels`` pixels (fewer for more than ``STRIP_CHANNELS`` channels;
    0: one strip). Returns ``(N, channels, h, w)``, contiguous and owning its memory.

    The strips are of the cropped image, as the plain graph's head sees it (an image of
    one strip gets its numbers bit for bit); while the groups are alive the result lives
    in the up-sampling's memory
    (:meth:`~mehs.ssr.net.strips.RowGroups.output_buffer`) and is copied out after.
    """
    f, h, w = features(net, x)
    n = f.shape[0]
    rows = channel_strip_rows(chunk_pixels, n, h, w, f.channels)
    borrowed = f.output_buffer(channels)
    if rows >= h and borrowed is None:
        # (one strip: its result is the output, not copied into another of its size)
        return strip(f.rows(0, h)[..., :w]).contiguous()
    out = (torch.empty((n, channels, h, w), dtype=f.dtype, device=f.device)
           if borrowed is None else borrowed[..., :h, :w])
    scratch = f.scratch(rows)
    for r0 in range(0, h, rows):
        r1 = min(h, r0 + rows)
        out[:, :, r0:r1] = strip(f.rows(r0, r1, scratch)[..., :w])
    if borrowed is None:
        return out
    del f, scratch, borrowed      # (the groups: the stored features but the output's)
    # a view of a wider map would hold its 48 channels for 31 as long as the caller
    # keeps the result, and is not contiguous for a cropped image
    return out.clone(memory_format=torch.contiguous_format)


def lean(net: FCDenseNet) -> bool:
    """Whether :func:`features` runs ``net`` in row groups: every part it calls directly
    is exactly the stock module, without hooks, and runs in strips at inference."""
    if not (_plain(net, FCDenseNet) and net.depth >= 1 and not net.training):
        return False
    first = net.first
    if not (type(first) is nn.Conv2d and first.padding_mode == "zeros"
            and isinstance(first.padding, tuple) and first.stride == (1, 1)
            and all(2 * p == d * (k - 1) for p, d, k in
                    zip(first.padding, first.dilation, first.kernel_size))):
        return False        # (the first convolution must keep the image's size)
    blocks = (net.down_blocks[0], net.up_blocks[-1])
    return (all(type(b) is DenseBlock and b.keep_input
                and all(type(layer) is DenseLayer and layer._strippable() for layer in b.layers)
                for b in blocks)
            and type(net.trans_down[0]) is TransitionDown and net.trans_down[0]._strippable()
            and type(net.trans_up[-1]) is nn.ConvTranspose2d)
