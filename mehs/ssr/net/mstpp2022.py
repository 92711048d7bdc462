"""MST++ (Cai et al. 2022): multi-stage spectral-wise transformer, NTIRE 2022 winner.

Layer by layer as the authors' ``MST_Plus_Plus`` (caiyuanhao1998/MST-plus-plus):
3×3 conv in (3 → C) → ``stage`` single-stage MSTs in sequence → 3×3 conv out
(C → L) + the conv-in features (global residual). Each MST is a U-shaped
encoder–decoder of spectral-wise multi-head self-attention blocks (MSAB):
embedding 3×3 conv; per level an MSAB then a 4×4 stride-2 conv doubling the
channels; a bottleneck MSAB; per level a 2×2 stride-2 transposed conv, a 1×1 fusion
conv with the skip, an MSAB; a 3×3 mapping conv + the MST's input.

An MSAB block is ``x + S-MSA(x)`` then ``x + FFN(LayerNorm(x))``. S-MSA treats each
channel as a token: per head (head dim = C), ``A = softmax(σ · K̂ Q̂ᵀ)`` over the
``d × d`` channel similarity of L2-normalised (over pixels) keys and queries, ``A V``,
a linear projection, plus a positional term: depth-wise 3×3 conv → GELU → depth-wise
3×3 conv applied to V. FFN: 1×1 conv (×4) → GELU → depth-wise 3×3 → GELU → 1×1 conv.
The cost is linear in the number of pixels.

Input ``(N, 3, H, W)``, padded (reflect; replicate for images smaller than the pad)
to a multiple of 8 and cropped back; output ``(N, L, H, W)``. The channel width is the
number of output bands (31), as in the authors' code: the global residual adds the
conv-in features to the output.

Full preset (3 stages, 2 levels, one block per MSAB): 1.62 M parameters with 31
bands, as the MST++ paper lists.

References
----------
- Cai, Y., Lin, J., Lin, Z., Wang, H., Zhang, Y., Pfister, H., Timofte, R., Van Gool,
  L. (2022). MST++: Multi-stage Spectral-wise Transformer for Efficient Spectral
  Reconstruction. CVPR Workshops.
- Cai, Y. et al. (2022). Mask-guided Spectral-wise Transformer for Efficient
  Hyperspectral Image Reconstruction. CVPR (the single-stage MST).
"""

from __future__ import annotations

from typing import Sequence

import torch
from torch import nn
import torch.nn.functional as F

from mehs.errors import InputError
from mehs.ssr.net import mstpp_lean
from mehs.ssr.net.base import NetConfig, SSRNetwork
from mehs.ssr.net.strips import conv2d_into, training_graph
from mehs.ssr.net.pooling import image_statistic, statistics_detached


#: Pixels per chunk of :meth:`SpectralMSA._similarity_sums` (a tile's owned part).
SIMILARITY_CHUNK = 1 << 16


class SpectralMSA(nn.Module):
    """Spectral-wise multi-head self-attention on ``(N, H, W, C)`` → ``(N, H, W, C)``."""

    #: its channel similarity is a sum over pixels (:meth:`_image_similarity`): tiles
    #: can run with the whole image's (:mod:`mehs.ssr.tiling_global`)
    image_statistics = True

    def __init__(self, dim: int, dim_head: int, heads: int):
        super().__init__()
        self.heads, self.dim_head = heads, dim_head
        inner = dim_head * heads
        if inner != dim:
            raise ValueError(f"S-MSA needs heads·dim_head == dim, got {heads}·{dim_head} != {dim}")
        self.to_q = nn.Linear(dim, inner, bias=False)
        self.to_k = nn.Linear(dim, inner, bias=False)
        self.to_v = nn.Linear(dim, inner, bias=False)
        self.rescale = nn.Parameter(torch.ones(heads, 1, 1))
        self.proj = nn.Linear(inner, dim, bias=True)
        self.pos_emb = nn.Sequential(
            nn.Conv2d(dim, dim, 3, 1, 1, bias=False, groups=dim), nn.GELU(),
            nn.Conv2d(dim, dim, 3, 1, 1, bias=False, groups=dim))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        n, h, w, c = x.shape
        tokens = x.reshape(n, h * w, c)
        v_inp = self.to_v(tokens)

        def heads_first(t):  # (n, hw, heads·d) → (n, heads, d, hw)
            return t.reshape(n, h * w, self.heads, self.dim_head).permute(0, 2, 3, 1)

        q_inp, k_inp = self.to_q(tokens), self.to_k(tokens)
        attn = self._image_similarity(k_inp, q_inp, h, w) if n == 1 else None
        if attn is None:
            q = F.normalize(heads_first(q_inp), dim=-1, p=2)
            k = F.normalize(heads_first(k_inp), dim=-1, p=2)
            attn = k @ q.transpose(-2, -1)
            if statistics_detached():
                # a receptive-field probe: the similarity sums over every pixel
                attn = attn.detach()
        v = heads_first(v_inp)
        attn = attn * self.rescale                        # (n, heads, d, d)
        out = attn.softmax(dim=-1) @ v                    # (n, heads, d, hw)
        out = out.permute(0, 3, 1, 2).reshape(n, h * w, self.heads * self.dim_head)
        out_c = self.proj(out).view(n, h, w, c)
        out_p = self.pos_emb(v_inp.reshape(n, h, w, c).permute(0, 3, 1, 2)).permute(0, 2, 3, 1)
        return out_c + out_p

    def _image_similarity(self, k_inp: torch.Tensor, q_inp: torch.Tensor, h: int,
                          w: int) -> torch.Tensor | None:
        """``K̂ Q̂ᵀ`` of the whole image while tiles run under image-wide statistics, else None.

        Its entries are sums over pixels, ``Σ k_i q_j / (‖k_i‖ ‖q_j‖)``, so tiles can
        assemble them (:func:`mehs.ssr.net.pooling.image_statistic`): the channel Gram
        matrix and squared norms of the image, as means over its pixels (the count
        cancels).
        """
        inner = self.heads * self.dim_head
        maps = tuple(t.view(1, h, w, inner).permute(0, 3, 1, 2) for t in (k_inp, q_inp))
        stats = image_statistic(self, maps, self._similarity_sums, self._cosines)
        if stats is None:
            return None
        return self._cosines(stats).to(dtype=k_inp.dtype, device=k_inp.device)

    def _cosines(self, stats: torch.Tensor) -> torch.Tensor:
        # (1, heads, d, d): Gram / (‖k_i‖ ‖q_j‖), as F.normalize's floor keeps 0 for 0
        nh, d = self.heads, self.dim_head
        gram = stats[:nh * d * d].view(1, nh, d, d)
        norms = stats[nh * d * d:].view(2, 1, nh, d).sqrt().clamp_min(1e-30)
        return gram / (norms[0][..., :, None] * norms[1][..., None, :])

    def _similarity_sums(self, k: torch.Tensor, q: torch.Tensor) -> torch.Tensor:
        """Per head the Gram matrix ``K Qᵀ``, then ``Σ k²`` and ``Σ q²``, flat (float64),
        over the pixels of ``(C, h, w)`` views of channels-last maps."""
        nh, d = self.heads, self.dim_head
        k, q = k.permute(1, 2, 0), q.permute(1, 2, 0)          # (h, w, C) views
        rows = max(1, SIMILARITY_CHUNK // max(1, k.shape[1]))
        total = torch.zeros(nh * d * (d + 2), dtype=torch.float64)
        # in row chunks: the owned part of a tile is a strided view, and a copy of all of
        # it (two maps of C channels) would add ~250 B/px to the tile's peak. Each chunk
        # in float32 at least (half floats overflow a Gram matrix; a float64 network keeps
        # its precision), the totals in float64 on the CPU (Apple's MPS devices have no
        # float64)
        dtype = torch.promote_types(k.dtype, torch.float32)
        for r in range(0, k.shape[0], rows):
            kc = k[r:r + rows].reshape(-1, nh, d).transpose(0, 1).to(dtype)   # (heads, P, d)
            qc = q[r:r + rows].reshape(-1, nh, d).transpose(0, 1).to(dtype)
            part = torch.cat([(kc.transpose(1, 2) @ qc).reshape(-1),
                              (kc * kc).sum(1).reshape(-1), (qc * qc).sum(1).reshape(-1)])
            total += part.to(device="cpu", dtype=torch.float64)
        return total


class FeedForward(nn.Module):
    """1×1 conv (×mult) → GELU → depth-wise 3×3 → GELU → 1×1 conv, on ``(N, H, W, C)``."""

    def __init__(self, dim: int, mult: int = 4):
        super().__init__()
        self.net = nn.Sequential(
            nn.Conv2d(dim, dim * mult, 1, 1, bias=False), nn.GELU(),
            nn.Conv2d(dim * mult, dim * mult, 3, 1, 1, bias=False, groups=dim * mult), nn.GELU(),
            nn.Conv2d(dim * mult, dim, 1, 1, bias=False))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.net(x.permute(0, 3, 1, 2)).permute(0, 2, 3, 1)


class MSAB(nn.Module):
    """``num_blocks`` × (S-MSA + residual, LayerNorm → FFN + residual) on ``(N, C, H, W)``."""

    #: Pixels per row strip at inference (:mod:`mehs.ssr.net.mstpp_lean`; 0: whole maps).
    chunk_pixels: int = mstpp_lean.STRIP_PIXELS

    def __init__(self, dim: int, dim_head: int, heads: int, num_blocks: int):
        super().__init__()
        self.attn = nn.ModuleList(SpectralMSA(dim, dim_head, heads) for _ in range(num_blocks))
        self.norm = nn.ModuleList(nn.LayerNorm(dim) for _ in range(num_blocks))
        self.ff = nn.ModuleList(FeedForward(dim) for _ in range(num_blocks))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        if self._strippable():
            return self.lean_forward(x, owned=False)
        x = x.permute(0, 2, 3, 1)
        for attn, norm, ff in zip(self.attn, self.norm, self.ff):
            x = attn(x) + x
            x = ff(norm(x)) + x
        return x.permute(0, 3, 1, 2)

    def lean_forward(self, x: torch.Tensor, *, owned: bool) -> torch.Tensor:
        """Inference in row strips (see :meth:`_strippable`): no image-sized temporaries
        (issue 16). ``owned``: ``x`` is the caller's to overwrite (the result is then ``x``)."""
        y = x
        for i, (attn, norm, ff) in enumerate(zip(self.attn, self.norm, self.ff)):
            out = y if (owned or i > 0) else torch.empty_like(y, memory_format=torch.contiguous_format)
            mstpp_lean.msa_residual(attn, y, out, self.chunk_pixels)
            y = out
            mstpp_lean.ffn_residual_(norm, ff, y, self.chunk_pixels)
        return y

    def _strippable(self) -> bool:
        """Inference whose parts are this module's own, as built (see :mod:`mstpp_lean`)."""
        if not mstpp_lean.lean_allowed((self, MSAB)):
            return False
        for attn, norm, ff in zip(self.attn, self.norm, self.ff):
            # the strips use the projections' weights (and proj's bias), two rows of
            # context for the positional term and one for the feed-forward block: the
            # parts as built, pointwise activations between the convolutions
            if not (type(attn) is SpectralMSA and type(norm) is nn.LayerNorm
                    and type(ff) is FeedForward
                    and all(type(m) is nn.Linear for m in (attn.to_q, attn.to_k, attn.to_v, attn.proj))
                    and all(m.bias is None for m in (attn.to_q, attn.to_k, attn.to_v))
                    and _layout(attn.pos_emb) == [(3, 1), "act", (3, 1)]
                    and _layout(ff.net) == [(1, 0), "act", (3, 1), "act", (1, 0)]):
                return False
        return True


def _layout(seq: nn.Module) -> list | None:
    """A ``Sequential`` of ``nn.Conv2d`` (as ``(kernel, padding)``: square, stride 1,
    zero-padded) and ``nn.GELU`` (``"act"``); None if it holds anything else."""
    if type(seq) is not nn.Sequential:
        return None
    out = []
    for m in seq:
        if type(m) is nn.GELU:
            out.append("act")
        elif (type(m) is nn.Conv2d and m.stride == (1, 1) and m.dilation == (1, 1)
              and m.padding_mode == "zeros" and isinstance(m.padding, tuple)
              and len(set(m.kernel_size)) == 1 and len(set(m.padding)) == 1):
            out.append((m.kernel_size[0], m.padding[0]))
        else:
            return None
    return out


class MST(nn.Module):
    """Single-stage U-shaped spectral transformer, ``(N, C, H, W)`` → ``(N, C, H, W)``;
    H and W must be multiples of ``2**levels``."""

    #: Pixels per row strip of the decoder's up-sampling and fusion at inference.
    chunk_pixels: int = mstpp_lean.STRIP_PIXELS

    def __init__(self, dim: int, levels: int, num_blocks: Sequence[int]):
        super().__init__()
        # down-samplings: the tile grid (mehs.ssr.tiling_probes.torch_align) is 2**depth
        self.depth = int(levels)
        if len(num_blocks) != levels + 1:
            raise ValueError(f"MST with {levels} levels needs {levels + 1} block counts")
        self.embedding = nn.Conv2d(dim, dim, 3, 1, 1, bias=False)
        self.encoder = nn.ModuleList()
        d = dim
        for i in range(levels):
            self.encoder.append(nn.ModuleList([
                MSAB(d, dim, d // dim, num_blocks[i]),
                nn.Conv2d(d, 2 * d, 4, 2, 1, bias=False)]))
            d *= 2
        self.bottleneck = MSAB(d, dim, d // dim, num_blocks[-1])
        self.decoder = nn.ModuleList()
        for i in range(levels):
            self.decoder.append(nn.ModuleList([
                nn.ConvTranspose2d(d, d // 2, kernel_size=2, stride=2),
                nn.Conv2d(d, d // 2, 1, 1, bias=False),
                MSAB(d // 2, dim, (d // 2) // dim, num_blocks[levels - 1 - i])]))
            d //= 2
        self.mapping = nn.Conv2d(dim, dim, 3, 1, 1, bias=False)
        self.apply(_init_weights)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        if self._strippable(x):
            return self._lean_forward(x)
        fea = self.embedding(x)
        skips = []
        for msab, down in self.encoder:
            fea = msab(fea)
            skips.append(fea)
            fea = down(fea)
        fea = self.bottleneck(fea)
        for (up, fuse, msab), skip in zip(self.decoder, skips[::-1]):
            fea = msab(fuse(torch.cat([up(fea), skip], dim=1)))
        return self.mapping(fea) + x

    def _strippable(self, x: torch.Tensor) -> bool:
        """Whether :meth:`_lean_forward` may run: its parts as built (it writes into the
        maps they return, which must be fresh) and a size the plain forward accepts."""
        m = 2 ** self.depth
        return (mstpp_lean.lean_allowed((self, MST)) and x.shape[-2] % m == 0
                and x.shape[-1] % m == 0
                and all(type(c) is nn.Conv2d for c in (self.embedding, self.mapping))
                and type(self.bottleneck) is MSAB
                and all(type(msab) is MSAB and type(down) is nn.Conv2d
                        for msab, down in self.encoder)
                and all(type(up) is nn.ConvTranspose2d and type(msab) is MSAB
                        and _layout(nn.Sequential(fuse)) == [(1, 0)] and fuse.groups == 1
                        for up, fuse, msab in self.decoder))

    def _lean_forward(self, x: torch.Tensor) -> torch.Tensor:
        # the plain forward's steps; each skip and map is released as soon as it is used
        def block(msab, fea):
            # every input here is a fresh map of this forward's: the blocks overwrite it
            return msab.lean_forward(fea, owned=True) if msab._strippable() else msab(fea)

        def conv(c, t, add=None):
            return conv2d_into(c, t, add=add, chunk_pixels=self.chunk_pixels)

        fea = conv(self.embedding, x)
        skips = []
        for msab, down in self.encoder:
            fea = block(msab, fea)
            skips.append(fea)
            fea = conv(down, fea)
        fea = block(self.bottleneck, fea)
        for up, fuse, msab in self.decoder:
            # (the lower level's map is released before the block runs)
            fea = mstpp_lean.up_fuse(up, fuse, fea, skips.pop(), self.chunk_pixels,
                                     into_skip=True)
            fea = block(msab, fea)
        return conv(self.mapping, fea, add=x)


def _init_weights(m: nn.Module) -> None:
    # the authors' initialisation: truncated normal (std 0.02) linear weights, zero biases
    if isinstance(m, nn.Linear):
        nn.init.trunc_normal_(m.weight, std=0.02)
        if m.bias is not None:
            nn.init.zeros_(m.bias)
    elif isinstance(m, nn.LayerNorm):
        nn.init.ones_(m.weight)
        nn.init.zeros_(m.bias)


class MSTPlusPlus2022(SSRNetwork):
    """MST++: ``stages`` MSTs of ``levels`` levels between a 3×3 conv in and a 3×3 conv out.

    Parameters (``params``): ``stages`` (3), ``levels`` (2), ``num_blocks``
    (``(1, 1, 1)``, one count per level plus the bottleneck).
    """

    #: Pixels per row strip of the full-resolution convolutions at inference.
    chunk_pixels: int = mstpp_lean.STRIP_PIXELS

    PRESETS = {
        "full": dict(stages=3, levels=2, num_blocks=(1, 1, 1)),
        "small": dict(stages=1, levels=1, num_blocks=(1, 1)),
        "tiny": dict(stages=1, levels=1, num_blocks=(1, 1)),
    }

    def __init__(self, config: NetConfig, *, stages: int = 3, levels: int = 2,
                 num_blocks: Sequence[int] = (1, 1, 1)):
        super().__init__(config)
        dim = self.n_bands
        num_blocks = tuple(int(b) for b in num_blocks)
        if len(num_blocks) != int(levels) + 1:
            raise InputError(f"MST++ with levels={levels} needs {int(levels) + 1} num_blocks, "
                             f"got {list(num_blocks)}")
        # the authors pad to a multiple of 8 (enough for up to 3 levels)
        self.multiple = max(8, 2 ** int(levels))
        self.conv_in = nn.Conv2d(3, dim, 3, padding=1, bias=False)
        self.body_stages = nn.Sequential(*(MST(dim, int(levels), num_blocks)
                                           for _ in range(int(stages))))
        self.conv_out = nn.Conv2d(dim, dim, 3, padding=1, bias=False)

    def body(self, x: torch.Tensor) -> torch.Tensor:
        h, w = x.shape[-2:]
        m = self.multiple
        pad_h, pad_w = (-h) % m, (-w) % m
        # the authors pad by reflection; reflection needs the pad to be smaller than the side
        mode = "reflect" if (pad_h < h and pad_w < w) else "replicate"
        x = F.pad(x, [0, pad_w, 0, pad_h], mode=mode)
        if training_graph():
            x = self.conv_in(x)
            return (self.conv_out(self.body_stages(x)) + x)[..., :h, :w]
        # inference: the full-resolution convolutions in row strips (no image-sized
        # reorders) and the global residual added strip by strip
        chunk = self.chunk_pixels
        x = conv2d_into(self.conv_in, x, chunk_pixels=chunk)
        out = conv2d_into(self.conv_out, self.body_stages(x), add=x, chunk_pixels=chunk)
        return out[..., :h, :w]
