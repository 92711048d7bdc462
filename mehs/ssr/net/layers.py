"""FC-DenseNet ("Tiramisu"): dense layers with dropout (Jégou et al. 2017, as
Galliani et al. 2017 and Mikamoto et al. use it) or with channel attention in place
of dropout (the HDR SSR paper, Fig. 6).

Shapes are PyTorch's ``(N, C, H, W)``. :class:`FCDenseNet` pads ``H`` and ``W``
up to a multiple of ``2**depth`` (replicate padding) and crops the features back,
so any image size works, odd ones included.

References
----------
- Jégou, S., Drozdzal, M., Vazquez, D., Romero, A., Bengio, Y. (2017). The One
  Hundred Layers Tiramisu: Fully Convolutional DenseNets for Semantic
  Segmentation. CVPR Workshops.
- Galliani, S., Lanaras, C., Marmanis, D., Baltsavias, E., Schindler, K. (2017).
  Learned Spectral Super-Resolution. arXiv:1703.09470.
- Hu, J., Shen, L., Sun, G. (2018). Squeeze-and-Excitation Networks. CVPR
  (the channel-attention block).
"""

from __future__ import annotations

from typing import Sequence

import torch
from torch import nn
import torch.nn.functional as F

from mehs.ssr.net.pooling import pooled_mean
from mehs.ssr.net.strips import (STRIP_PIXELS, RowGroups, _plain, conv_transpose_into,
                                 strip_pixels, training_graph)


class ChannelAttention(nn.Module):
    """Squeeze-and-excitation: GAP → 1×1 conv to ``C/r`` → ReLU → 1×1 conv to ``C`` → sigmoid → × input.

    With ``zero_init=True`` the last convolution starts at zero weights and bias,
    so the block initially multiplies every channel by exactly ``sigmoid(0) = 0.5``.
    """

    #: its global mean goes through :func:`~mehs.ssr.net.pooling.pooled_mean`: tiles
    #: can run with the whole image's (:mod:`mehs.ssr.tiling_global`)
    image_statistics = True

    def __init__(self, channels: int, reduction: int = 4, *, zero_init: bool = False):
        super().__init__()
        hidden = max(1, channels // reduction)
        self.squeeze = nn.Conv2d(channels, hidden, kernel_size=1)
        self.excite = nn.Conv2d(hidden, channels, kernel_size=1)
        if zero_init:
            nn.init.zeros_(self.excite.weight)
            nn.init.zeros_(self.excite.bias)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return x * self.weights(x)

    def weights(self, x: torch.Tensor) -> torch.Tensor:
        """The per-channel factors ``(N, C, 1, 1)`` the block multiplies ``x`` by."""
        # (the image-wide mean when tiles run under mehs.ssr.net.pooling.ImageMeans)
        s = pooled_mean(self, x)
        return torch.sigmoid(self.excite(F.relu(self.squeeze(s))))


def _inference_bn(bn: nn.Module) -> bool:
    """A BatchNorm that normalises with its running statistics (per pixel, so strips can)."""
    return (_plain(bn, nn.BatchNorm2d) and not bn.training and bn.track_running_stats
            and bn.running_mean is not None)


def _strippable_conv(seq: nn.Sequential, cls: type) -> nn.Conv2d | None:
    """The convolution of ``seq`` (exactly a ``cls``: BN → ReLU → conv → ...) when its
    BN → ReLU → conv may run in strips at inference (see :func:`_plain`,
    :func:`_inference_bn`), else None; the caller checks the conv's shape."""
    if not (_plain(seq, cls) and not seq.training):
        return None
    bn, relu, conv = seq[0], seq[1], seq[2]
    if _inference_bn(bn) and type(relu) is nn.ReLU and type(conv) is nn.Conv2d:
        return conv
    return None


def _strip_rows(chunk_pixels: int, x: torch.Tensor, multiple: int = 1) -> int:
    """Rows per strip of ``x`` ``(N, C, H, W)`` (a multiple of ``multiple``); ``H`` or more:
    no strips. Wide maps get fewer pixels per strip (:func:`~mehs.ssr.net.strips.strip_pixels`:
    a strip's normalised copy and oneDNN's reorder of it are ``C`` wide)."""
    n, c, h, w = x.shape
    if chunk_pixels <= 0:
        return h
    return max(multiple, strip_pixels(chunk_pixels, c) // max(1, n * w) // multiple * multiple)


class DenseLayer(nn.Sequential):
    """BN → ReLU → 3×3 conv (``growth`` channels) → channel attention (``attention``,
    the paper's layer) or dropout ``p = dropout`` (Jégou's original layer)."""

    chunk_pixels: int = STRIP_PIXELS

    def __init__(self, in_channels: int, growth: int, reduction: int = 4, *,
                 attention: bool = True, dropout: float = 0.0):
        layers = [nn.BatchNorm2d(in_channels), nn.ReLU(inplace=True),
                  nn.Conv2d(in_channels, growth, kernel_size=3, padding=1, bias=False)]
        if attention:
            layers.append(ChannelAttention(growth, reduction))
        if dropout > 0:
            layers.append(nn.Dropout(dropout))
        super().__init__(*layers)

    def _strippable(self) -> bool:
        conv = _strippable_conv(self, DenseLayer)
        return (conv is not None and conv.stride == (1, 1) and conv.dilation == (1, 1)
                and conv.padding_mode == "zeros" and isinstance(conv.padding, tuple)
                and 2 * conv.padding[0] == conv.kernel_size[0] - 1
                and all(type(m) in (ChannelAttention, nn.Dropout) for m in list(self)[3:]))

    def run_into(self, src: torch.Tensor | RowGroups, dst: torch.Tensor) -> None:
        """Inference: this layer on ``src`` ``(N, c, H, W)`` (a tensor or
        :class:`~mehs.ssr.net.strips.RowGroups`), written into ``dst`` ``(N, g, H, W)``.

        BN → ReLU → conv run in row strips of about ``chunk_pixels`` pixels, each with
        the convolution's rows of context on either side (zeros beyond the image, as
        the convolution's own padding): the same sums per output pixel. The channel
        attention then scales ``dst`` in place.
        """
        groups = src if isinstance(src, RowGroups) else RowGroups.of(src)
        rows = _strip_rows(self.chunk_pixels, groups)
        h = groups.shape[2]
        # (row groups run as one strip rather than be concatenated for the whole call)
        if not self._strippable() or (rows >= h and len(groups.groups) == 1):
            dst[...] = self(groups.whole())
            return
        rows = min(rows, h)
        bn, conv = self[0], self[2]
        k = conv.padding[0]
        scratch = groups.scratch(rows + 2 * k)
        for r0 in range(0, h, rows):
            r1 = min(h, r0 + rows)
            a, b = max(0, r0 - k), min(h, r1 + k)
            # rows the conv pads beyond the strip's context are discarded, except at the
            # image's edges, where they are the conv's own zero padding
            y = conv(groups.normalized(bn, a, b, scratch))
            dst[:, :, r0:r1] = y[:, :, r0 - a:r1 - a]
            del y               # (else two strips are alive while the next is computed)
        for m in list(self)[3:]:
            if isinstance(m, ChannelAttention):
                dst.mul_(m.weights(dst))
            # (dropout is the identity at inference)


class DenseBlock(nn.Module):
    """``n_layers`` dense layers; each sees the concatenation of the block input and all
    earlier layers' outputs. Returns the concatenation of the new features only
    (``n_layers·growth`` channels) or, with ``keep_input``, input + new features."""

    def __init__(self, in_channels: int, n_layers: int, growth: int, reduction: int = 4,
                 *, keep_input: bool = False, attention: bool = True, dropout: float = 0.0):
        super().__init__()
        self.keep_input = keep_input
        self.layers = nn.ModuleList(
            DenseLayer(in_channels + i * growth, growth, reduction, attention=attention,
                       dropout=dropout) for i in range(n_layers))
        self.growth, self.new_channels = growth, n_layers * growth
        self.out_channels = (in_channels if keep_input else 0) + self.new_channels

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        if training_graph():
            feats = [x]
            for layer in self.layers:
                feats.append(layer(torch.cat(feats, dim=1)))
            return torch.cat(feats if self.keep_input else feats[1:], dim=1)
        return self.fill(self.buffer(x))

    # Inference: each layer writes its features into one preallocated tensor and the
    # next reads a channel prefix of it (contiguous for N = 1), instead of
    # re-concatenating everything before every layer: the same numbers without the
    # quadratic copies, which were most of the peak memory of a large image (issue 16).
    def buffer(self, *inputs: torch.Tensor) -> torch.Tensor:
        """A tensor for the block's input and features, ``inputs`` copied in along channels."""
        x0 = inputs[0]
        c_in = sum(int(t.shape[1]) for t in inputs)
        buf = x0.new_empty(x0.shape[0], c_in + self.new_channels, x0.shape[2], x0.shape[3])
        c = 0
        for t in inputs:
            buf[:, c:c + t.shape[1]] = t
            c += t.shape[1]
        return buf

    def fill(self, buf: torch.Tensor) -> torch.Tensor:
        """Run the layers on a :meth:`buffer`; the block's output (a view of it)."""
        c_in = c = buf.shape[1] - self.new_channels
        for layer in self.layers:
            layer.run_into(buf[:, :c], buf[:, c:c + self.growth])
            c += self.growth
        # a view of the new channels would keep the whole buffer alive (its inputs: 5×
        # the new channels in the small paper network) until the next block is built
        return buf if self.keep_input else buf[:, c_in:].clone()

    def empty_buffer(self, like: torch.Tensor, in_channels: int) -> torch.Tensor:
        """An uninitialised :meth:`buffer` for ``in_channels`` input channels of ``like``'s size."""
        n, _, h, w = like.shape
        return like.new_empty(n, in_channels + self.new_channels, h, w)


class MaxPool2x2(nn.MaxPool2d):
    """``nn.MaxPool2d(2)``; at inference the maximum of the four strided quarter views.

    CPU ``max_pool2d`` also computes int64 indices it then drops: 5× slower on a
    full-resolution 32-channel map (75 vs 14 ms at 768×1024, 5 % of the small paper
    network's forward). The maximum of the same four values is the same number (NaN
    included); training, tracing and export keep the stock operator.
    """

    def __init__(self):
        super().__init__(2)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        if training_graph() or x.dim() != 4:
            return super().forward(x)
        h, w = x.shape[-2] // 2 * 2, x.shape[-1] // 2 * 2     # floor, as max_pool2d
        x = x[..., :h, :w]
        out = torch.maximum(x[..., 0::2, 0::2], x[..., 1::2, 0::2])
        torch.maximum(out, x[..., 0::2, 1::2], out=out)     # one output-sized tensor
        return torch.maximum(out, x[..., 1::2, 1::2], out=out)


class TransitionDown(nn.Sequential):
    """BN → ReLU → 1×1 conv → (dropout) → 2×2 max-pool (halves H and W).

    At inference every step is per pixel up to the pooling, so the transition runs
    in strips of an even number of rows (``chunk_pixels`` pixels, see
    :data:`STRIP_PIXELS`): the same numbers without its full-resolution temporaries.
    """

    chunk_pixels: int = STRIP_PIXELS

    def __init__(self, channels: int, dropout: float = 0.0):
        layers = [nn.BatchNorm2d(channels), nn.ReLU(inplace=True),
                  nn.Conv2d(channels, channels, kernel_size=1, bias=False)]
        if dropout > 0:
            layers.append(nn.Dropout(dropout))
        super().__init__(*layers, MaxPool2x2())

    def _strippable(self) -> bool:
        conv = _strippable_conv(self, TransitionDown)
        return (conv is not None and conv.kernel_size == (1, 1) and conv.stride == (1, 1)
                and conv.padding == (0, 0) and type(self[-1]) is MaxPool2x2
                and all(type(m) is nn.Dropout for m in list(self)[3:-1]))

    def forward(self, x: torch.Tensor | RowGroups) -> torch.Tensor:
        """``x``: a tensor, or (at inference) :class:`~mehs.ssr.net.strips.RowGroups`."""
        groups = x if isinstance(x, RowGroups) else None
        if groups is not None and not self._strippable():
            x, groups = groups.whole(), None
        if groups is None and (training_graph() or x.dim() != 4 or not self._strippable()):
            return super().forward(x)
        src = groups or RowGroups.of(x)
        rows = _strip_rows(self.chunk_pixels, src, multiple=2)
        if rows >= src.shape[2] and groups is None:
            return super().forward(x)
        bn, conv, rest = self[0], self[2], list(self)[3:]     # (dropouts, the pooling)
        n, _, h, w = src.shape
        out = torch.empty((n, conv.out_channels, h // 2, w // 2), dtype=src.dtype,
                          device=src.device)
        scratch = src.scratch(rows)
        for r0 in range(0, h // 2 * 2, rows):
            r1 = min(h // 2 * 2, r0 + rows)
            y = conv(src.normalized(bn, r0, r1, scratch))
            for m in rest:
                y = m(y)
            out[:, :, r0 // 2:r1 // 2] = y
        return out


class FCDenseNet(nn.Module):
    """FC-DenseNet encoder–decoder feature extractor.

    Parameters
    ----------
    in_channels
        Input channels (3 for RGB).
    first_channels
        Channels of the first 3×3 convolution.
    down_layers
        Dense layers per block on the way down; ``depth = len(down_layers)``
        poolings, so ``H`` and ``W`` are padded to a multiple of ``2**depth``.
    bottleneck_layers
        Dense layers of the bottleneck block.
    growth
        Growth rate (channels each dense layer adds).
    reduction
        Channel-attention reduction ratio ``r``.
    attention, dropout
        Dense layers with channel attention (the paper's) and/or dropout ``p``
        (Jégou's original: ``attention=False, dropout=0.2``).

    Input ``(N, in_channels, H, W)``; output ``(N, out_channels, H, W)``.
    """

    #: Output pixels per row strip of the up-sampling at inference (:func:`conv_transpose_into`).
    chunk_pixels: int = STRIP_PIXELS

    def __init__(self, in_channels: int = 3, *, first_channels: int = 16,
                 down_layers: Sequence[int] = (2, 2, 2), bottleneck_layers: int = 2,
                 growth: int = 8, reduction: int = 4, attention: bool = True,
                 dropout: float = 0.0):
        super().__init__()
        if not 0.0 <= float(dropout) < 1.0:
            raise ValueError(f"dropout must be in [0, 1), got {dropout}")
        opts = dict(attention=bool(attention), dropout=float(dropout))
        self.depth = len(down_layers)
        self.first = nn.Conv2d(in_channels, first_channels, kernel_size=3, padding=1)
        self.down_blocks = nn.ModuleList()
        self.trans_down = nn.ModuleList()
        skips = []
        c = first_channels
        for n in down_layers:
            block = DenseBlock(c, n, growth, reduction, keep_input=True, **opts)
            self.down_blocks.append(block)
            c = block.out_channels
            skips.append(c)
            self.trans_down.append(TransitionDown(c, float(dropout)))
        self.bottleneck = DenseBlock(c, bottleneck_layers, growth, reduction, **opts)
        up_in = self.bottleneck.out_channels
        self.trans_up = nn.ModuleList()
        self.up_blocks = nn.ModuleList()
        up_layers = list(down_layers)[::-1]
        for i, (n, skip) in enumerate(zip(up_layers, skips[::-1])):
            self.trans_up.append(nn.ConvTranspose2d(up_in, up_in, kernel_size=3, stride=2,
                                                    padding=1, output_padding=1))
            last = i == len(up_layers) - 1
            block = DenseBlock(up_in + skip, n, growth, reduction, keep_input=last, **opts)
            self.up_blocks.append(block)
            up_in = block.out_channels
        self.out_channels = up_in

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        h, w = x.shape[-2], x.shape[-1]
        m = 2 ** self.depth
        # (-h) % m works on traced sizes too, so the ONNX graph keeps dynamic H, W.
        pad_h, pad_w = (-h) % m, (-w) % m
        x = F.pad(x, (0, pad_w, 0, pad_h), mode="replicate")
        x = self.first(x)
        skips = []
        for block, down in zip(self.down_blocks, self.trans_down):
            x = block(x)
            skips.append(x)
            x = down(x)
        x = self.bottleneck(x)
        if training_graph():
            for up, block, skip in zip(self.trans_up, self.up_blocks, skips[::-1]):
                x = block(torch.cat([up(x), skip], dim=1))
            return x[..., :h, :w]
        for up, block in zip(self.trans_up, self.up_blocks):
            held = [x]
            del x
            x = self.up_step(up, block, held, skips)
        return x[..., :h, :w]

    def up_step(self, up: nn.Module, block: nn.Module, held: list, skips: list) -> torch.Tensor:
        """Inference: one level of the decoder on the features in ``held`` and the last
        of ``skips``, both popped (so that the caller holds neither while it runs)."""
        x = held.pop()
        if not _plain(block, DenseBlock):
            # a subclass or a forward hook sees (and may replace) the block's call
            return block(torch.cat([up(x), skips.pop()], dim=1))
        # the skip, then the up-sampled features, go straight into the block's buffer
        # and each is released before the next is made (a concatenation, and a skip
        # kept to the end, held ~200 B/px more at full resolution)
        skip = skips.pop()
        c_up, c_skip = up.out_channels, skip.shape[1]
        buf = block.empty_buffer(skip, c_up + c_skip)
        buf[:, c_up:c_up + c_skip] = skip
        del skip
        conv_transpose_into(up, x, buf[:, :c_up], self.chunk_pixels)
        del x
        # (the result is a copy of the new channels, or all of the buffer)
        return block.fill(buf)
