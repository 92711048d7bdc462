"""Row strips for inference (issue 16): what decides whether a network may run its
per-pixel work in strips, how large a strip is, and convolutions evaluated a strip of
output rows at a time with exactly the whole call's products.

A whole-map CPU convolution reorders a copy of its input into oneDNN's blocked layout,
and a transposed convolution gathers through a column buffer of ``C_out·k²`` values per
input pixel; in strips those temporaries are a few MB and stay in cache. Used by the
FC-DenseNet layers (:mod:`mehs.ssr.net.layers`), MST++ (:mod:`mehs.ssr.net.mstpp_lean`),
HSCNN-D and Galliani's head.

Shapes are PyTorch's ``(N, C, H, W)``; everything here is inference only.
"""

from __future__ import annotations

import torch
from torch import nn
import torch.nn.functional as F

from mehs.ssr.net.pooling import compiling, plain_graph_wanted


#: Pixels per row strip in which inference runs a dense layer's or a transition's
#: per-pixel work (their ``chunk_pixels``; 0: whole maps). A strip's normalised input
#: and oneDNN's reordered copy of it stay in cache instead of costing two image-sized
#: temporaries, which set the peak memory of a large image (issue 16).
STRIP_PIXELS = 65536


#: Channels ``chunk_pixels`` pixels are counted for where a strip's temporaries have
#: many more or fewer channels (:func:`channel_strip_rows`).
STRIP_CHANNELS = 128


def strip_pixels(chunk_pixels: int, channels: int) -> int:
    """Pixels per strip whose temporaries have ``channels`` channels:
    ``chunk_pixels · min(1, STRIP_CHANNELS / channels)``."""
    return chunk_pixels * STRIP_CHANNELS // max(STRIP_CHANNELS, channels)


def channel_strip_rows(chunk_pixels: int, n: int, h: int, w: int, channels: int) -> int:
    """Rows per strip of an ``(n, ·, h, w)`` map whose strip temporaries have ``channels``
    channels: ``chunk_pixels · min(1, STRIP_CHANNELS / channels)`` pixels, so that strips of
    wide maps (an HSCNN-D block reading 1056 channels) hold no more than others (0: all
    rows). Never more than ``chunk_pixels``: the memory probe sees every module in several
    strips on its probe two chunks large (:func:`mehs.ssr.tiling_probes.torch_memory_probe`)."""
    if chunk_pixels <= 0:
        return h
    return max(1, min(h, strip_pixels(chunk_pixels, channels) // max(1, n * w)))


def _plain(module: nn.Module, *types: type) -> bool:
    """Whether ``module`` is exactly one of ``types`` (not a subclass, whose forward may
    differ) and neither it, its children nor the process carry forward hooks: the
    strips call its parts' functions directly, past hooks and overridden forwards."""
    return type(module) in types and not hooked(module)


def hooked(module: nn.Module) -> bool:
    """Whether a forward hook (the process's, or one of ``module``'s or its children's) is set."""
    from torch.nn.modules import module as _m

    return bool(_m._global_forward_hooks or _m._global_forward_pre_hooks) or any(
        m._forward_hooks or m._forward_pre_hooks for m in module.modules())


def training_graph() -> bool:
    """True where autograd, forward-mode differentiation (:func:`mehs.ssr.net.pooling.plain_graph`),
    an exporter or a compiler needs the plain concatenating graph (``torch.export`` and
    ``torch.compile`` would unroll the strips' Python loops for one image size)."""
    # the compiler's test first: dynamo folds it to a constant, and reading the plain
    # graph's ContextVar while compiling is a graph break at every call
    return (compiling() or torch.is_grad_enabled() or plain_graph_wanted()
            or torch.jit.is_tracing() or torch.onnx.is_in_onnx_export() or _autocast())


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


class RowGroups:
    """An ``(N, C, H, W)`` map held as channel groups, each stored (a tensor ``(N, c, H, W)``)
    or computed for the rows asked (``f(a, b) -> (N, c, b - a, W)``, e.g. a cheap first
    convolution): read a row strip at a time, it costs a strip, not an image-sized
    concatenation (issue 16: FC-DenseNet56's last block held 192 full-resolution
    channels, of which 96 were its skip and 48 its first convolution's).

    ``owned`` marks stored groups no one else holds: :meth:`output_buffer` may hand one
    to a per-pixel consumer of this map to write its result into.
    """

    def __init__(self, groups, like: torch.Tensor, height: int, width: int, *, owned=()):
        self.groups = [(int(c), g) for c, g in groups]
        self.channels = sum(c for c, _ in self.groups)
        self.shape = torch.Size((like.shape[0], self.channels, height, width))
        self.dtype, self.device = like.dtype, like.device
        self._owned = tuple(owned)

    @classmethod
    def of(cls, x: torch.Tensor) -> "RowGroups":
        """One stored group: ``x`` itself."""
        return cls([(x.shape[1], x)], x, x.shape[2], x.shape[3])

    def prefix(self, channels: int) -> "RowGroups":
        """The first ``channels`` channels (a computed group is taken whole or not at all)."""
        kept, c = [], 0
        for ch, g in self.groups:
            if c >= channels:
                break
            take = min(ch, channels - c)
            if take < ch:
                if callable(g):
                    raise ValueError(f"a prefix of {channels} channels cuts a computed group")
                g = g[:, :take]
            kept.append((take, g))
            c += take
        if c < channels:
            raise ValueError(f"a prefix of {channels} channels of a map of {self.channels}")
        return RowGroups(kept, self._like(), self.shape[2], self.shape[3], owned=self._owned)

    def _like(self) -> torch.Tensor:
        return torch.empty((self.shape[0], 0, 0, 0), dtype=self.dtype, device=self.device)

    def _part(self, g, a: int, b: int) -> torch.Tensor:
        return g(a, b) if callable(g) else g[:, :, a:b]

    def _strip(self, rows: int, scratch: torch.Tensor | None) -> torch.Tensor:
        shape = (self.shape[0], self.channels, rows, self.shape[3])
        n = shape[0] * shape[1] * shape[2] * shape[3]
        if scratch is not None and scratch.numel() >= n and scratch.dtype == self.dtype:
            return scratch[:n].view(shape)
        return torch.empty(shape, dtype=self.dtype, device=self.device)

    def scratch(self, rows: int) -> torch.Tensor | None:
        """Memory for strips of up to ``rows`` rows, for the ``scratch`` of :meth:`rows`
        and :meth:`normalized` (None for one stored group, whose strips are views):
        a consumer's strips then reuse one block instead of leaving the C heap a
        fragment per strip (0.1–0.2 GB resident in FC-DenseNet56's last level)."""
        if len(self.groups) == 1:
            return None
        n = self.shape[0] * self.channels * min(rows, self.shape[2]) * self.shape[3]
        return torch.empty(n, dtype=self.dtype, device=self.device)

    def rows(self, a: int, b: int, scratch: torch.Tensor | None = None) -> torch.Tensor:
        """Rows ``a:b`` of the whole map ``(N, C, b - a, W)`` (a view for one stored group;
        else in ``scratch`` (:meth:`scratch`) if given and large enough)."""
        if len(self.groups) == 1:
            return self._part(self.groups[0][1], a, b)
        out = self._strip(b - a, scratch)
        c = 0
        for ch, g in self.groups:
            out[:, c:c + ch] = self._part(g, a, b)
            c += ch
        return out

    def whole(self) -> torch.Tensor:
        return self.rows(0, self.shape[2])

    def normalized(self, bn: nn.BatchNorm2d, a: int, b: int,
                   scratch: torch.Tensor | None = None) -> torch.Tensor:
        """``relu(bn(rows(a, b)))`` for an inference batch norm (running statistics),
        each group normalised straight into its channels of one strip tensor (in
        ``scratch`` as for :meth:`rows`)."""
        if len(self.groups) == 1:
            return F.relu(bn(self.rows(a, b)), inplace=True)
        # each group through torch's own batch norm (the plain graph's numbers bit for
        # bit), written straight into its channels of the strip where they are contiguous
        # (N = 1); the strip's concatenation would be one more pass
        out = self._strip(b - a, scratch)
        # (the statistics' dtype: a float32 batch norm of a bfloat16 network saves float32)
        none = bn.running_mean.new_empty(0)
        c = 0
        for ch, g in self.groups:
            sl = slice(c, c + ch)
            w = None if bn.weight is None else bn.weight.detach()[sl]
            bias = None if bn.bias is None else bn.bias.detach()[sl]
            part, mean, var = self._part(g, a, b), bn.running_mean[sl], bn.running_var[sl]
            if not part.is_contiguous() and part.stride(1) <= part.stride(3):
                # channels innermost (channels-last): the kernel would write that layout
                # into the NCHW strip (0.15-0.63 off)
                part = part.contiguous()
            dst = out[:, sl]
            if dst.is_contiguous():
                torch.ops.aten.native_batch_norm.out(part, w, bias, mean, var, False, 0.0,
                                                     bn.eps, out=dst, save_mean=none,
                                                     save_invstd=none)
            else:
                dst.copy_(F.batch_norm(part, mean, var, w, bias, False, 0.0, bn.eps))
            c += ch
        return out.relu_()

    def output_buffer(self, channels: int) -> torch.Tensor | None:
        """``(1, channels, H, W)`` in the memory of a stored group this map owns, or None.

        Only for a consumer that is per pixel and writes a strip of rows after reading
        every group's same rows (a 1×1 head): those rows are never read again. The
        result then needs no image-sized allocation while the groups are alive (its
        consumer copies it out once they are freed: :func:`~mehs.ssr.net.fcdensenet_lean.head`).
        """
        if self.shape[0] != 1:
            return None          # (a channel slice of a batch is not contiguous)
        for ch, g in self.groups:
            if (not callable(g) and any(g is o for o in self._owned) and ch >= channels
                    and g.is_contiguous()):
                return g[:, :channels]
        return None


def _bias_rows(up: nn.ConvTranspose2d, x: torch.Tensor, shape) -> torch.Tensor:
    out = x.new_zeros(shape)
    if up.bias is not None:
        out += up.bias.view(1, -1, 1, 1)
    return out
