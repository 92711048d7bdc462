"""AWAN (Li et al. 2020): adaptive weighted attention network, NTIRE 2020 "Clean" winner.

Layer by layer as the authors' ``AWAN`` (Deep-imagelab/AWAN; the 4.04 M-parameter
configuration the MST++ authors benchmark, ``channels = 96``, 8 DRABs): every conv
is bias-free with reflection padding; PReLU activations.

- head: 3×3 conv (3 → C) → PReLU → 3×3 conv; ``residual = res = out``;
- 8 dual residual attention blocks (DRAB): ``x_r = x``; 3×3 conv → PReLU → 3×3 conv,
  ``+ x_r`` → PReLU; 5×5 conv ``+ res`` → PReLU, ``res = x``; AWCA; 3×3 conv ``+ x_r``
  → PReLU;
- tail: 3×3 conv ``+ residual`` → PReLU → 3×3 conv (C → L) → PSNL.

AWCA (adaptive weighted channel attention): a 1×1 conv (C → 1) and a softmax over all
pixels give spatial weights; the weighted sum of each channel → FC (C → C/16) → PReLU
→ FC → sigmoid scales the channels. PSNL (patch-level second-order non-local): the
output is cut into 2×2 quadrants; in each, with ``θ = W_θ x`` and ``g = W_g x``
(1×1, C → C/8), ``f = (θ − mean_c θ) θᵀ / (C/8)`` (pixels × pixels), ``y = softmax(f) g``,
``z = x + W_z y`` with ``W_z`` zero-initialised. ``f`` has (H·W/4)² entries, so it is
evaluated with :func:`torch.nn.functional.scaled_dot_product_attention` (query
``(θ − mean θ)/(C/8)``, key ``θ``, value ``g``, scale 1), which never forms it; the
cost stays quadratic in the pixels (the reason for AWAN's 325 s in the paper's Table 5).

Input ``(N, 3, H, W)`` with ``H, W ≥ 3`` (reflection padding of the 5×5 conv); output
``(N, L, H, W)``.

References
----------
- Li, J., Wu, C., Song, R., Li, Y., Liu, F. (2020). Adaptive Weighted Attention Network
  with Camera Spectral Sensitivity Prior for Spectral Reconstruction from RGB Images.
  CVPR Workshops.
- Wang, X., Girshick, R., Gupta, A., He, K. (2018). Non-local Neural Networks. CVPR.
"""

from __future__ import annotations

import numpy as np
import torch
from torch import nn
import torch.nn.functional as F

from mehs.ssr.net.base import NetConfig, SSRNetwork


class ReflectConv(nn.Sequential):
    """Reflection padding then a bias-free ``k × k`` conv (the authors' ``Conv3x3``)."""

    def __init__(self, c_in: int, c_out: int, k: int):
        super().__init__(nn.ReflectionPad2d((k - 1) // 2), nn.Conv2d(c_in, c_out, k, bias=False))


class AWCA(nn.Module):
    """Adaptive weighted channel attention, ``(N, C, H, W)`` → same shape."""

    def __init__(self, channels: int, reduction: int = 16):
        super().__init__()
        self.conv = nn.Conv2d(channels, 1, 1, bias=False)
        hidden = max(1, channels // reduction)
        self.fc = nn.Sequential(nn.Linear(channels, hidden, bias=False), nn.PReLU(),
                                nn.Linear(hidden, channels, bias=False), nn.Sigmoid())

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        n, c, h, w = x.shape
        weights = self.conv(x).view(n, h * w, 1).softmax(dim=1)   # (n, hw, 1)
        y = torch.bmm(x.reshape(n, c, h * w), weights).view(n, c)  # weighted mean per channel
        return x * self.fc(y).view(n, c, 1, 1)


class SecondOrderNonLocal(nn.Module):
    """Non-local block with the second-order (covariance) affinity, ``(N, C, H, W)``."""

    def __init__(self, channels: int, reduction: int = 8):
        super().__init__()
        self.inter = max(1, channels // reduction)
        self.g = nn.Conv2d(channels, self.inter, 1, bias=False)
        self.theta = nn.Conv2d(channels, self.inter, 1, bias=False)
        self.W = nn.Conv2d(self.inter, channels, 1, bias=False)
        nn.init.zeros_(self.W.weight)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        n, _, h, w = x.shape
        g = self.g(x).flatten(2).transpose(1, 2)        # (n, hw, c')
        th = self.theta(x).flatten(2).transpose(1, 2)   # (n, hw, c')
        q = (th - th.mean(dim=2, keepdim=True)) / self.inter
        y = F.scaled_dot_product_attention(q, th, g, scale=1.0)  # softmax(q thᵀ) g
        return x + self.W(y.transpose(1, 2).reshape(n, self.inter, h, w))


class PSNL(nn.Module):
    """The non-local block applied to each quadrant of the image separately."""

    def __init__(self, channels: int):
        super().__init__()
        self.non_local = SecondOrderNonLocal(channels)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        h1, w1 = x.shape[-2] // 2, x.shape[-1] // 2
        rows = []
        for band in (x[..., :h1, :], x[..., h1:, :]):
            parts = [p if p.numel() == 0 else self.non_local(p)
                     for p in (band[..., :w1], band[..., w1:])]
            rows.append(torch.cat(parts, dim=-1))
        return torch.cat(rows, dim=-2)


class DRAB(nn.Module):
    """Dual residual attention block; ``forward(x, res) -> (x, res)``."""

    def __init__(self, channels: int, k1: int = 5, k2: int = 3, reduction: int = 16):
        super().__init__()
        self.conv1 = ReflectConv(channels, channels, 3)
        self.relu1 = nn.PReLU()
        self.conv2 = ReflectConv(channels, channels, 3)
        self.relu2 = nn.PReLU()
        self.up_conv = ReflectConv(channels, channels, k1)
        self.up_relu = nn.PReLU()
        self.se = AWCA(channels, reduction)
        self.down_conv = ReflectConv(channels, channels, k2)
        self.down_relu = nn.PReLU()

    def forward(self, x: torch.Tensor, res: torch.Tensor):
        x_r = x
        x = self.relu2(self.conv2(self.relu1(self.conv1(x))) + x_r)
        x = self.up_relu(self.up_conv(x) + res)
        res = x
        x = self.down_relu(self.down_conv(self.se(x)) + x_r)
        return x, res


class AWAN2020(SSRNetwork):
    """AWAN. Parameters (``params``): ``channels`` (96), ``n_blocks`` (8 DRABs)."""

    PRESETS = {
        "full": dict(channels=96, n_blocks=8),
        "small": dict(channels=32, n_blocks=2),
        "tiny": dict(channels=16, n_blocks=1),
    }
    #: The paper trains AWAN with a lower cosine-annealing range (η_max 2e-4, η_min 1e-5).
    RECIPE = dict(lr_max=2e-4, lr_min=1e-5)
    #: Tiled inference (mehs.ssr.tiling): the non-local block is global, so no receptive
    #: radius can be probed (the probe itself would run out of memory); a fixed margin
    TILING_MARGIN = 32

    @staticmethod
    def max_tile_pixels(max_bytes: int) -> int:
        """Largest tile (pixels) whose non-local attention fits ``max_bytes``.

        PSNL attends over each quarter of its input: an ``(n/4)²`` float32 affinity
        matrix, about three copies alive (scores, softmax, its product) — memory
        grows with the *square* of the tile, which a per-pixel probe cannot see
        (a 2048×1024 image at once would ask ~1 TiB).
        """
        return max(64 * 64, int(4 * np.sqrt(max_bytes / 12.0)))

    def __init__(self, config: NetConfig, *, channels: int = 96, n_blocks: int = 8):
        super().__init__(config)
        c = int(channels)
        self.input_conv = ReflectConv(3, c, 3)
        self.input_prelu = nn.PReLU()
        self.head_conv = ReflectConv(c, c, 3)
        self.backbone = nn.ModuleList(DRAB(c) for _ in range(int(n_blocks)))
        self.tail_conv = ReflectConv(c, c, 3)
        self.output_prelu = nn.PReLU()
        self.output_conv = ReflectConv(c, self.n_bands, 3)
        self.tail_nonlocal = PSNL(self.n_bands)

    def body(self, x: torch.Tensor) -> torch.Tensor:
        out = self.head_conv(self.input_prelu(self.input_conv(x)))
        residual = res = out
        for block in self.backbone:
            out, res = block(out, res)
        out = self.tail_conv(out) + residual
        return self.tail_nonlocal(self.output_conv(self.output_prelu(out)))
