"""MST++ inference in row strips (issue 16): the numbers of the plain graph, without its
full-resolution temporaries.

The plain MST++ graph holds, per spectral-wise attention block, the queries, keys,
values, their normalised copies, the attention output, its projection and the
positional term as image-sized maps, and per feed-forward block four maps of 4·C
channels (its expansion): 4.4 GB at 2048×1024 for the published size, most of it
temporaries of per-pixel work. Here

- the channel similarity ``K̂ Q̂ᵀ`` is summed over row chunks (Gram matrix and squared
  norms of keys and queries computed from the block's input, float64 totals; with the
  tiles' image-wide statistics when they run under
  :class:`mehs.ssr.net.pooling.ImageMeans`, as the plain graph does);
- ``proj(A V) + pos_emb(V) + x`` is evaluated per row strip, the values of each strip
  and the two rows of context either side its two 3×3 depth-wise convolutions need;
  ``proj ∘ A`` is one ``C × C`` matrix (a product of the same weights);
- ``x + FFN(LayerNorm(x))`` per row strip with one row of context; both residual steps
  write into the block's own buffer in place, each strip once no later strip reads its
  rows as context;
- the decoder's up-sampling, concatenation with the skip and 1×1 fusion per strip.

Only the stage's input, the block's buffer and a skip per level stay image-sized (MST++
full at 2048×1024: 4.4 → 1.7 GB peak). Sums run in
another order than in the plain graph (chunks; ``proj ∘ A`` folded): the results agree
to float32 rounding, not bit for bit.

Shapes: maps ``(N, C, H, W)``; every function here is inference only (no autograd).
"""

from __future__ import annotations

import torch
from torch import nn
import torch.nn.functional as F

from mehs.ssr.net.strips import (STRIP_PIXELS, _plain, channel_strip_rows, conv_transpose_rows,
                                 training_graph)
from mehs.ssr.net.pooling import image_statistic


def lean_allowed(*modules: tuple[nn.Module, type]) -> bool:
    """Whether inference may run in strips: no autograd, forward-mode probe, tracing or
    export, and each ``(module, type)`` exactly of that type with no hooks (strips call
    the parts' weights directly, past overridden forwards and hooks)."""
    return not training_graph() and all(_plain(m, t) for m, t in modules)


def _rows(x: torch.Tensor, chunk_pixels: int, channels: int) -> int:
    """Rows per strip of ``x`` ``(N, C, H, W)`` whose temporaries have ``channels`` channels
    (:func:`~mehs.ssr.net.strips.channel_strip_rows`: the bottleneck's feed-forward strips,
    4 × 124 channels, are no larger than the first level's, 4 × 31; a fixed pixel count
    made them 0.4 GB, the peak of MST++ full)."""
    n, _, h, w = x.shape
    return channel_strip_rows(chunk_pixels, n, h, w, channels)


def _pointwise(x: torch.Tensor, weight: torch.Tensor, bias: torch.Tensor | None = None) -> torch.Tensor:
    """A 1×1 convolution (or a linear layer's ``(out, in)`` weight) on ``(N, C, h, w)``."""
    return F.conv2d(x, weight.reshape(weight.shape[0], -1, 1, 1), bias)


def similarity_sums(msa, x: torch.Tensor, chunk_pixels: int = STRIP_PIXELS) -> torch.Tensor:
    """:meth:`SpectralMSA._similarity_sums` of the keys and queries of ``x``'s pixels
    (``(C, h, w)``), computed a row chunk at a time from ``x``."""
    c, h, w = x.shape
    # (a chunk holds its keys, queries and their squares)
    rows = _rows(x[None], chunk_pixels, 4 * c)
    total = None
    for r in range(0, h, rows):
        part = x[None, :, r:r + rows]
        k = _pointwise(part, msa.to_k.weight)[0]
        q = _pointwise(part, msa.to_q.weight)[0]
        s = msa._similarity_sums(k, q)
        total = s if total is None else total + s
        del k, q
    return total


def _mixing(msa, x: torch.Tensor, chunk_pixels: int, *, image_wide: bool) -> torch.Tensor:
    """``proj.weight · blockdiag(softmax(σ · K̂ Q̂ᵀ))`` of one image ``x`` ``(1, C, h, w)``:
    the ``C × C`` map from a pixel's values to its attention output (before the bias).
    ``image_wide``: the tiles' image-wide similarity where they run under image means."""
    def sums(part):
        return similarity_sums(msa, part, chunk_pixels)

    stats = image_statistic(msa, (x,), sums, msa._cosines) if image_wide else None
    if stats is None:
        stats = sums(x[0])
    cos = msa._cosines(stats).to(dtype=x.dtype, device=x.device)       # (1, heads, d, d)
    attn = (cos * msa.rescale).softmax(dim=-1)[0]
    return msa.proj.weight @ torch.block_diag(*attn)


class _LateRows:
    """Writes row strips into ``dst`` once no later strip reads those rows any more.

    In-place strips: a strip's convolutions read rows of context above it that earlier
    strips own, which must still hold the input when it is computed.
    """

    def __init__(self, dst: torch.Tensor):
        self.dst, self.pending = dst, []

    def before_reading(self, a: int) -> None:
        """The next strip reads rows ``a:``: write the strips that end at or above ``a``."""
        keep = []
        for r0, r1, values in self.pending:
            if r1 <= a:
                self.dst[:, :, r0:r1] = values
            else:
                keep.append((r0, r1, values))
        self.pending = keep

    def put(self, r0: int, r1: int, values: torch.Tensor) -> None:
        self.pending.append((r0, r1, values))

    def flush(self) -> None:
        self.before_reading(self.dst.shape[2])


def msa_residual(msa, x: torch.Tensor, out: torch.Tensor, chunk_pixels: int = STRIP_PIXELS) -> None:
    """``out = msa(x) + x`` for a :class:`~mehs.ssr.net.mstpp2022.SpectralMSA` ``msa`` on
    NCHW maps; ``out`` is a tensor of ``x``'s shape, or ``x`` itself (in place)."""
    n, c, h, _ = x.shape
    # (a strip holds its values, the positional term's three maps and the output)
    rows = _rows(x, chunk_pixels, 5 * c)
    # the positional term's two 3×3 depth-wise convolutions: two rows of context
    halo = 2
    # a batch's images each have their own similarity (the tiles' image-wide one is
    # for a single image, as in the plain graph)
    mix = [_mixing(msa, x[i:i + 1], chunk_pixels, image_wide=n == 1) for i in range(n)]
    late = _LateRows(out)
    for r0 in range(0, h, rows):
        r1 = min(h, r0 + rows)
        a, b = max(0, r0 - halo), min(h, r1 + halo)
        late.before_reading(a)
        v = _pointwise(x[:, :, a:b], msa.to_v.weight)
        pos = msa.pos_emb(v)[:, :, r0 - a:r1 - a]
        core = v[:, :, r0 - a:r1 - a]
        o = torch.cat([_pointwise(core[i:i + 1], m, msa.proj.bias) for i, m in enumerate(mix)]) \
            if n > 1 else _pointwise(core, mix[0], msa.proj.bias)
        o += pos
        o += x[:, :, r0:r1]
        late.put(r0, r1, o)
        # (the strip's temporaries would be alive while the next strip's are made)
        del v, pos, core, o
    late.flush()


def ffn_residual_(norm: nn.LayerNorm, ff, y: torch.Tensor, chunk_pixels: int = STRIP_PIXELS) -> None:
    """``y += FFN(LayerNorm(y))`` in place (``y`` NCHW, owned by the caller) for a
    :class:`~mehs.ssr.net.mstpp2022.FeedForward` ``ff``."""
    h = y.shape[2]
    expand, act1, depthwise, act2, reduce = ff.net
    rows = _rows(y, chunk_pixels, expand.out_channels)
    late = _LateRows(y)
    for r0 in range(0, h, rows):
        r1 = min(h, r0 + rows)
        a, b = max(0, r0 - 1), min(h, r1 + 1)
        late.before_reading(a)
        t = F.layer_norm(y[:, :, a:b].permute(0, 2, 3, 1), norm.normalized_shape, norm.weight,
                         norm.bias, norm.eps).permute(0, 3, 1, 2)
        t = act2(depthwise(act1(expand(t))))[:, :, r0 - a:r1 - a]
        res = reduce(t)
        res += y[:, :, r0:r1]
        late.put(r0, r1, res)
        del t, res
    late.flush()


def up_fuse(up: nn.ConvTranspose2d, fuse: nn.Conv2d, fea: torch.Tensor, skip: torch.Tensor,
            chunk_pixels: int = STRIP_PIXELS, *, into_skip: bool = False) -> torch.Tensor:
    """``fuse(cat([up(fea), skip], 1))`` per row strip (the decoder's step; ``fuse`` 1×1).

    ``into_skip``: the result overwrites ``skip`` (the caller's to give up, and of the
    result's shape): each strip reads only its own rows of it.
    """
    n, _, h, w = skip.shape
    if into_skip and skip.shape[1] == fuse.out_channels:
        out = skip
    else:
        out = skip.new_empty(n, fuse.out_channels, h, w)
    rows = _rows(skip, chunk_pixels, up.out_channels + skip.shape[1])
    for r0 in range(0, h, rows):
        r1 = min(h, r0 + rows)
        u = conv_transpose_rows(up, fea, r0, r1)
        # (the concatenation is a copy, so the strip of skip may be overwritten)
        out[:, :, r0:r1] = F.conv2d(torch.cat([u, skip[:, :, r0:r1]], dim=1), fuse.weight,
                                    fuse.bias)
        del u
    return out
