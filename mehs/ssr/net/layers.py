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

from mehs.ssr.net.pooling import plain_graph_wanted, pooled_mean


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


#: Pixels per row strip in which inference runs a dense layer's or a transition's
#: per-pixel work (their ``chunk_pixels``; 0: whole maps). A strip's normalised input
#: and oneDNN's reordered copy of it stay in cache instead of costing two image-sized
#: temporaries, which set the peak memory of a large image (issue 16).
STRIP_PIXELS = 65536


#: Channels ``chunk_pixels`` pixels are counted for where a strip's temporaries have
#: many more or fewer channels (:func:`channel_strip_rows`).
STRIP_CHANNELS = 128


def channel_strip_rows(chunk_pixels: int, n: int, h: int, w: int, channels: int) -> int:
    """Rows per strip of an ``(n, ·, h, w)`` map whose strip temporaries have ``channels``
    channels: ``chunk_pixels · min(1, STRIP_CHANNELS / channels)`` pixels, so that strips of
    wide maps (an HSCNN-D block reading 1056 channels) hold no more than others (0: all
    rows). Never more than ``chunk_pixels``: the memory probe sees every module in several
    strips on its probe two chunks large (:func:`mehs.ssr.tiling_probes.torch_memory_probe`)."""
    if chunk_pixels <= 0:
        return h
    pixels = chunk_pixels * STRIP_CHANNELS // max(STRIP_CHANNELS, channels)
    return max(1, min(h, pixels // max(1, n * w)))


def _plain(module: nn.Module, *types: type) -> bool:
    """Whether ``module`` is exactly one of ``types`` (not a subclass, whose forward may
    differ) and neither it, its children nor the process carry forward hooks: the
    strips call its parts' functions directly, past hooks and overridden forwards."""
    from torch.nn.modules import module as _m

    if type(module) not in types or _m._global_forward_hooks or _m._global_forward_pre_hooks:
        return False
    return not any(m._forward_hooks or m._forward_pre_hooks for m in module.modules())


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
    """Rows per strip of ``x`` ``(N, C, H, W)`` (a multiple of ``multiple``); ``H`` or more: no strips."""
    n, _, h, w = x.shape
    if chunk_pixels <= 0:
        return h
    return max(multiple, chunk_pixels // max(1, n * w) // multiple * multiple)


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

    def run_into(self, src: torch.Tensor, dst: torch.Tensor) -> None:
        """Inference: this layer on ``src`` ``(N, c, H, W)``, written into ``dst`` ``(N, g, H, W)``.

        BN → ReLU → conv run in row strips of about ``chunk_pixels`` pixels, each with
        the convolution's rows of context on either side (zeros beyond the image, as
        the convolution's own padding): the same sums per output pixel. The channel
        attention then scales ``dst`` in place.
        """
        rows = _strip_rows(self.chunk_pixels, src)
        h = src.shape[2]
        if rows >= h or not self._strippable():
            dst[...] = self(src)
            return
        bn, conv = self[0], self[2]
        k = conv.padding[0]
        for r0 in range(0, h, rows):
            r1 = min(h, r0 + rows)
            a, b = max(0, r0 - k), min(h, r1 + k)
            # rows the conv pads beyond the strip's context are discarded, except at the
            # image's edges, where they are the conv's own zero padding
            y = conv(F.relu(bn(src[:, :, a:b]), inplace=True))
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


def training_graph() -> bool:
    """True where autograd, forward-mode differentiation (:func:`mehs.ssr.net.pooling.plain_graph`)
    or an exporter needs the plain concatenating graph."""
    return (torch.is_grad_enabled() or plain_graph_wanted() or torch.jit.is_tracing()
            or torch.onnx.is_in_onnx_export() or _autocast())


#: Device types whose autocast state :func:`autocast_state` reads.
AUTOCAST_DEVICES = ("cpu", "cuda", "mps", "xpu")


def autocast_state() -> tuple:
    """``(device type, dtype)`` of every autocast region active here."""
    active = []
    for d in AUTOCAST_DEVICES:
        try:
            if torch.is_autocast_enabled(d):
                active.append((d, str(torch.get_autocast_dtype(d))))
        except (RuntimeError, ValueError):       # a device type this build does not know
            continue
    return tuple(active)


def _autocast() -> bool:
    # strips write into buffers of the input's dtype, where autocast's operators return
    # lower precision: the plain graph keeps its dtypes
    return bool(autocast_state())


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

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        if training_graph() or x.dim() != 4 or not self._strippable():
            return super().forward(x)
        rows = _strip_rows(self.chunk_pixels, x, multiple=2)
        conv = self[2]
        if rows >= x.shape[2]:
            return super().forward(x)
        n, _, h, w = x.shape
        out = x.new_empty(n, conv.out_channels, h // 2, w // 2)
        for r0 in range(0, h // 2 * 2, rows):
            r1 = min(h // 2 * 2, r0 + rows)
            out[:, :, r0 // 2:r1 // 2] = super().forward(x[:, :, r0:r1])
        return out


def conv_transpose_into(up: nn.Module, x: torch.Tensor, dst: torch.Tensor,
                        chunk_pixels: int = STRIP_PIXELS) -> None:
    """Inference: ``dst[...] = up(x)`` for an ``nn.ConvTranspose2d`` ``up``, in row strips
    of about ``chunk_pixels`` output pixels (:func:`conv_transpose_rows`).

    CPU transposed convolutions gather through a column buffer of ``C_out·k²`` values
    per *input* pixel (0.9 GB for FC-DenseNet56's last up-sampling at 2048×1024, the
    peak of its whole-image inference, issue 16); a strip's is a few MB. A module that
    is not plain (a subclass, hooks) runs whole, as does a ``dst`` not of the call's
    shape (which then raises as the plain assignment would).
    """
    n, h_out = x.shape[0], dst.shape[2]
    rows = max(1, chunk_pixels // max(1, n * dst.shape[3])) if chunk_pixels > 0 else h_out
    if (rows >= h_out or not _plain(up, nn.ConvTranspose2d) or dst.numel() == 0
            or dst.shape != conv_transpose_shape(up, x)):
        # (an empty or mismatched destination: the whole call, which raises as it would)
        dst[...] = up(x)
        return
    for o0 in range(0, h_out, rows):
        o1 = min(h_out, o0 + rows)
        dst[:, :, o0:o1] = conv_transpose_rows(up, x, o0, o1)


def conv_transpose_shape(up: nn.ConvTranspose2d, x: torch.Tensor) -> torch.Size:
    """The shape of ``up(x)`` (no ``output_size``)."""
    h, w = (
        (x.shape[2 + i] - 1) * up.stride[i] - 2 * up.padding[i]
        + up.dilation[i] * (up.kernel_size[i] - 1) + up.output_padding[i] + 1 for i in (0, 1))
    return torch.Size((x.shape[0], up.out_channels, h, w))


def conv_transpose_rows(up: nn.ConvTranspose2d, x: torch.Tensor, o0: int, o1: int) -> torch.Tensor:
    """Rows ``o0:o1`` of ``up(x)`` (``x`` ``(N, C, h, w)``), from the input rows that reach them.

    Output row ``o`` receives input row ``i`` where ``o = i·s − p + j·d`` (``j < k``): the
    strip's products are exactly the whole call's; rows no input row reaches hold the
    bias, as in the whole call.
    """
    (k, _), (s, sw), (p, pw), (d, dw) = up.kernel_size, up.stride, up.padding, up.dilation
    h_in = x.shape[2]
    a = max(0, -(-(o0 + p - (k - 1) * d) // s))                # ceil
    b = min(h_in - 1, (o1 - 1 + p) // s)
    shape = conv_transpose_shape(up, x[:, :, :1])
    out_shape = (shape[0], shape[1], o1 - o0, shape[3])
    if a > b:                                                  # no input row reaches them
        return _bias_rows(up, x, out_shape)
    y = F.conv_transpose2d(x[:, :, a:b + 1], up.weight, up.bias, (s, sw), (0, pw),
                           (0, up.output_padding[1]), up.groups, (d, dw))
    top = a * s - p                            # the global row of the strip's local row 0
    lo, hi = max(o0, top), min(o1, top + y.shape[2])
    if lo == o0 and hi == o1:
        return y[:, :, o0 - top:o1 - top]
    out = _bias_rows(up, x, out_shape)
    if hi > lo:
        out[:, :, lo - o0:hi - o0] = y[:, :, lo - top:hi - top]
    return out


def conv2d_into(conv: nn.Conv2d, x: torch.Tensor, out: torch.Tensor | None = None, *,
                add: torch.Tensor | None = None, chunk_pixels: int = STRIP_PIXELS) -> torch.Tensor:
    """Inference: ``conv(x)`` (``+ add``) in row strips of about ``chunk_pixels`` output
    pixels (:func:`conv2d_rows`), into ``out`` if given (not ``x``'s memory).

    A whole-map CPU convolution reorders its input into oneDNN's blocked layout and its
    output back: one more image-sized map at the call (0.26 GB for 31 channels at
    2048×1024); a strip's stays in cache. A convolution that is not a plain zero-padded
    ``nn.Conv2d`` runs whole.
    """
    n, _, h, w = x.shape
    plain = _plain(conv, nn.Conv2d) and conv.padding_mode == "zeros" and isinstance(conv.padding, tuple)
    if plain and chunk_pixels > 0:
        (k, kw), (s, sw), (p, pw), (d, dw) = conv.kernel_size, conv.stride, conv.padding, conv.dilation
        h_out = (h + 2 * p - d * (k - 1) - 1) // s + 1
        w_out = (w + 2 * pw - dw * (kw - 1) - 1) // sw + 1
        # (a strip's input and output, each reordered by oneDNN)
        rows = channel_strip_rows(chunk_pixels, n, h_out, w_out,
                                  max(conv.in_channels, conv.out_channels))
    if not plain or chunk_pixels <= 0 or rows >= h_out:
        # (one strip would be the whole call, with a padded copy of the input)
        y = conv(x)
        if add is not None:
            y = y + add
        if out is None:
            return y
        out[...] = y
        return out
    if out is None:
        out = x.new_empty(n, conv.out_channels, h_out, w_out)
    for o0 in range(0, h_out, rows):
        o1 = min(h_out, o0 + rows)
        y = conv2d_rows(conv, x, o0, o1)
        if add is not None:
            y += add[:, :, o0:o1]
        out[:, :, o0:o1] = y
        del y                   # (else two strips are alive while the next is computed)
    return out


def conv2d_rows(conv: nn.Conv2d, x: torch.Tensor, o0: int, o1: int) -> torch.Tensor:
    """Rows ``o0:o1`` of a zero-padded ``conv(x)``: the input rows they read, zero rows
    where those lie beyond the image (the convolution's own padding)."""
    (k, _), (s, sw), (p, pw), (d, dw) = conv.kernel_size, conv.stride, conv.padding, conv.dilation
    h = x.shape[2]
    lo, hi = o0 * s - p, (o1 - 1) * s - p + d * (k - 1) + 1          # input rows read
    a = min(h, max(0, lo))
    part = x[:, :, a:max(a, min(h, hi))]
    top, bottom = max(0, min(hi, 0) - lo), max(0, hi - max(lo, h))
    if top or bottom:
        part = F.pad(part, (0, 0, top, bottom))
    return F.conv2d(part, conv.weight, conv.bias, (s, sw), (0, pw), (d, dw), conv.groups)


def _bias_rows(up: nn.ConvTranspose2d, x: torch.Tensor, shape) -> torch.Tensor:
    out = x.new_zeros(shape)
    if up.bias is not None:
        out += up.bias.view(1, -1, 1, 1)
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
            if not _plain(block, DenseBlock):
                # a subclass or a forward hook sees (and may replace) the block's call
                x = block(torch.cat([up(x), skips.pop()], dim=1))
                continue
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
            x = block.fill(buf)
            del buf                    # (x is a copy of its new channels, or all of it)
        return x[..., :h, :w]
