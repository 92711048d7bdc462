"""HSCNN-D (Shi et al. 2018): densely connected CNN with path-widening fusion, NTIRE
2018 "Clean" winner.

Layer by layer as the implementation the MST++ authors benchmark (``HSCNN_Plus`` in
caiyuanhao1998/MST-plus-plus, whose ``dfus_block``/``ddfn`` are the dense fusion
blocks of HSCNN-D): every conv bias-free, ReLU after each.

- feature extraction: two paths from RGB, 3×3 conv (→ 32) → 1×1 conv (→ 32) each;
  their four outputs are concatenated (128 channels);
- ``n_blocks`` dense fusion blocks: 1×1 conv (→ 128); two widened paths, 3×3 conv
  (→ 32) → 1×1 conv (→ 16); the four path outputs (96) → 1×1 fusion conv (→ 32);
  the block's output is its input with those 32 channels appended;
- reconstruction: 1×1 conv (128 + 32·n → L).

Purely local: one output pixel depends on the ``1 + n_blocks`` pixels around it
(one 3×3 conv per block along each path), so tiled inference with that much
overlap is exact (:func:`mehs.ssr.net.infer.predict_tiled`; a model's tiles are planned
from the memory budget with the field measured, :mod:`mehs.ssr.tiling`). Without gradients
the image is swept down its rows as a wavefront (:mod:`~mehs.ssr.net.hscnnd_stream`:
every feature row computed once, a window of rows alive, memory growing with the
width only). A network with parts of its own (a subclass, hooks) writes its dense
features into one preallocated tensor instead of re-concatenating them after every
block (the same numbers, linear instead of quadratic copying).

Full preset: 30 blocks, 4.65 M parameters (the MST++ paper's table, "HSCNN+").

References
----------
- Shi, Z., Chen, C., Xiong, Z., Liu, D., Wu, F. (2018). HSCNN+: Advanced CNN-Based
  Hyperspectral Recovery from RGB Images. CVPR Workshops (HSCNN-D).
- Cai, Y. et al. (2022). MST++, CVPR Workshops (Table of parameter counts).
"""

from __future__ import annotations

import torch
from torch import nn

from mehs.ssr.net import hscnnd_stream
from mehs.ssr.net.base import NetConfig, SSRNetwork
from mehs.ssr.net.strips import (STRIP_PIXELS, _plain, channel_strip_rows, conv2d_into,
                                 training_graph)


def _conv(c_in: int, c_out: int, k: int) -> nn.Conv2d:
    return nn.Conv2d(c_in, c_out, k, 1, k // 2, bias=False)


class DenseFusionBlock(nn.Module):
    """1×1 compress → two (3×3 → 1×1) paths → 1×1 fusion; returns the new channels only."""

    def __init__(self, c_in: int, compress: int = 128, path: int = 32, path_out: int = 16,
                 fuse: int = 32):
        super().__init__()
        self.conv1 = _conv(c_in, compress, 1)
        self.up1, self.up2 = _conv(compress, path, 3), _conv(path, path_out, 1)
        self.down1, self.down2 = _conv(compress, path, 3), _conv(path, path_out, 1)
        self.fusion = _conv(2 * (path + path_out), fuse, 1)
        self.relu = nn.ReLU(inplace=True)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        r = self.relu
        f = r(self.conv1(x))
        u1 = r(self.up1(f))
        d1 = r(self.down1(f))
        cat = torch.cat([u1, r(self.up2(u1)), d1, r(self.down2(d1))], dim=1)
        return r(self.fusion(cat))

    def run_into(self, src: torch.Tensor, dst: torch.Tensor, chunk_pixels: int) -> None:
        """Inference: ``dst[...] = self(src)`` in row strips of about ``chunk_pixels`` pixels.

        Only the two 3×3 convolutions see neighbours (of the compressed map, zero-padded
        at the image's edges), so a strip with one row of context either side gives the
        whole call's sums. A whole-map call held the compression's oneDNN-reordered
        copy of its input, up to 1056 channels in the full preset (issue 16).
        """
        n, c, h, w = src.shape
        # (the strip of the block's input is copied and reordered: up to 1056 channels)
        rows = channel_strip_rows(chunk_pixels, n, h, w, max(c, self.conv1.out_channels))
        if rows >= h or not _strippable(self):
            dst[...] = self(src)
            return
        for r0 in range(0, h, rows):
            r1 = min(h, r0 + rows)
            a, b = max(0, r0 - 1), min(h, r1 + 1)
            dst[:, :, r0:r1] = self(src[:, :, a:b])[:, :, r0 - a:r1 - a]


def _strippable(block: "DenseFusionBlock") -> bool:
    # exactly this block, 3×3 convolutions zero-padded by one and everything else 1×1
    # (strips of one row of context), no hooks
    if not _plain(block, DenseFusionBlock):
        return False
    for name in BLOCK_CONVS:
        if not plain_conv(getattr(block, name), 3 if name in ("up1", "down1") else 1):
            return False
    return type(block.relu) is nn.ReLU


#: A dense fusion block's convolutions.
BLOCK_CONVS = ("conv1", "up1", "up2", "down1", "down2", "fusion")


def plain_conv(c: nn.Module, k: int) -> bool:
    """Exactly an ``nn.Conv2d`` of a ``k × k`` kernel, stride and dilation 1, zero-padded
    by ``k // 2`` (its output rows are its input's, read with ``k // 2`` rows of context)."""
    return (type(c) is nn.Conv2d and c.kernel_size == (k, k) and c.stride == (1, 1)
            and c.dilation == (1, 1) and c.padding == (k // 2, k // 2)
            and c.padding_mode == "zeros")


class HSCNND2018(SSRNetwork):
    """HSCNN-D. Parameters (``params``): ``n_blocks`` (30), ``head`` (32, per path conv),
    ``compress`` (128), ``path`` (32), ``path_out`` (16), ``fuse`` (32, channels each
    block adds)."""

    #: Pixels per row strip of the blocks and the output convolution at inference.
    chunk_pixels: int = STRIP_PIXELS

    PRESETS = {
        "full": dict(n_blocks=30, head=32, compress=128, path=32, path_out=16, fuse=32),
        "small": dict(n_blocks=6, head=16, compress=32, path=16, path_out=8, fuse=16),
        "tiny": dict(n_blocks=2, head=8, compress=16, path=8, path_out=4, fuse=8),
    }

    def __init__(self, config: NetConfig, *, n_blocks: int = 30, head: int = 32,
                 compress: int = 128, path: int = 32, path_out: int = 16, fuse: int = 32):
        super().__init__(config)
        n_blocks, head, fuse = int(n_blocks), int(head), int(fuse)
        self.up1, self.up2 = _conv(3, head, 3), _conv(head, head, 1)
        self.down1, self.down2 = _conv(3, head, 3), _conv(head, head, 1)
        self.relu = nn.ReLU(inplace=True)
        c0 = 4 * head
        self.blocks = nn.ModuleList(
            DenseFusionBlock(c0 + i * fuse, int(compress), int(path), int(path_out), fuse)
            for i in range(n_blocks))
        self.c0, self.fuse = c0, fuse
        self.conv_out = _conv(c0 + n_blocks * fuse, self.n_bands, 1)
        self.receptive_radius = 1 + n_blocks

    def stream_window_rows(self, width: int) -> int:
        """Rows of all feature channels inference keeps alive (fewer in an image not as
        tall: :mod:`~mehs.ssr.net.hscnnd_stream`); 0 where it keeps the dense features."""
        return hscnnd_stream.window_rows(self) if hscnnd_stream.streamable(self) else 0

    def body(self, x: torch.Tensor) -> torch.Tensor:
        if not training_graph() and hscnnd_stream.wanted(self, x):
            return hscnnd_stream.forward(self, x)
        r = self.relu
        u1, d1 = r(self.up1(x)), r(self.down1(x))
        feats = torch.cat([u1, r(self.up2(u1)), d1, r(self.down2(d1))], dim=1)
        if training_graph():
            for block in self.blocks:
                feats = torch.cat([feats, block(feats)], dim=1)
            return self.conv_out(feats)
        n, _, h, w = x.shape
        total = self.c0 + len(self.blocks) * self.fuse
        buf = x.new_empty(n, total, h, w)
        buf[:, :self.c0] = feats
        c = self.c0
        for block in self.blocks:
            if isinstance(block, DenseFusionBlock):
                block.run_into(buf[:, :c], buf[:, c:c + self.fuse], self.chunk_pixels)
            else:                               # a module put in its place runs as it is
                buf[:, c:c + self.fuse] = block(buf[:, :c])
            c += self.fuse
        return conv2d_into(self.conv_out, buf, chunk_pixels=self.chunk_pixels)
