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


class ChannelAttention(nn.Module):
    """Squeeze-and-excitation: GAP → 1×1 conv to ``C/r`` → ReLU → 1×1 conv to ``C`` → sigmoid → × input.

    With ``zero_init=True`` the last convolution starts at zero weights and bias,
    so the block initially multiplies every channel by exactly ``sigmoid(0) = 0.5``.
    """

    def __init__(self, channels: int, reduction: int = 4, *, zero_init: bool = False):
        super().__init__()
        hidden = max(1, channels // reduction)
        self.squeeze = nn.Conv2d(channels, hidden, kernel_size=1)
        self.excite = nn.Conv2d(hidden, channels, kernel_size=1)
        if zero_init:
            nn.init.zeros_(self.excite.weight)
            nn.init.zeros_(self.excite.bias)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        # (the image-wide mean when tiles run under mehs.ssr.net.pooling.ImageMeans)
        s = pooled_mean(self, x)
        s = torch.sigmoid(self.excite(F.relu(self.squeeze(s))))
        return x * s


class DenseLayer(nn.Sequential):
    """BN → ReLU → 3×3 conv (``growth`` channels) → channel attention (``attention``,
    the paper's layer) or dropout ``p = dropout`` (Jégou's original layer)."""

    def __init__(self, in_channels: int, growth: int, reduction: int = 4, *,
                 attention: bool = True, dropout: float = 0.0):
        layers = [nn.BatchNorm2d(in_channels), nn.ReLU(inplace=True),
                  nn.Conv2d(in_channels, growth, kernel_size=3, padding=1, bias=False)]
        if attention:
            layers.append(ChannelAttention(growth, reduction))
        if dropout > 0:
            layers.append(nn.Dropout(dropout))
        super().__init__(*layers)


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
            buf[:, c:c + self.growth] = layer(buf[:, :c])
            c += self.growth
        return buf if self.keep_input else buf[:, c_in:]


def training_graph() -> bool:
    """True where autograd or an exporter needs the plain concatenating graph."""
    return torch.is_grad_enabled() or torch.jit.is_tracing() or torch.onnx.is_in_onnx_export()


class TransitionDown(nn.Sequential):
    """BN → ReLU → 1×1 conv → (dropout) → 2×2 max-pool (halves H and W)."""

    def __init__(self, channels: int, dropout: float = 0.0):
        layers = [nn.BatchNorm2d(channels), nn.ReLU(inplace=True),
                  nn.Conv2d(channels, channels, kernel_size=1, bias=False)]
        if dropout > 0:
            layers.append(nn.Dropout(dropout))
        super().__init__(*layers, nn.MaxPool2d(2))


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
            # the up-sampled features and the skip go straight into the block's buffer
            # and are released before its layers run (a concatenation, and a skip kept
            # to the end, held ~200 B/px more at full resolution)
            buf = block.buffer(up(x), skips.pop())
            del x
            x = block.fill(buf)
        return x[..., :h, :w]
