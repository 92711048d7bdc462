"""Mikamoto et al.'s two-branch SSR network: FC-DenseNet features → sigmoid-basis and
Mexican-hat-basis branches → 1×1 fusion (no attention; dense layers with dropout).

The paper's own network (:mod:`mehs.ssr.net.hdrssr`) is this one with channel
attention in place of dropout, so both share :class:`TwoBranchFCDenseNet`.

Shapes: ``body(x (N, 3, H, W)) -> (N, L, H, W)`` (``L`` output bands); the branches
evaluate ``F(λ) = Σ_i w_i f_i(λ)`` (n = 10 bases each) per pixel.

References
----------
- Mikamoto et al., the multiple-branch network of basis functions (reference [16] of
  the HDR SSR paper): the two-branch variant with sigmoid functions and Mexican hat
  wavelets, the best combination of their study.
- Jégou, S. et al. (2017). The One Hundred Layers Tiramisu: Fully Convolutional
  DenseNets for Semantic Segmentation. CVPR Workshops.
- Jakob, W., Hanika, J. (2019). A low-dimensional function space for efficient
  spectral upsampling. Computer Graphics Forum 38(2).
"""

from __future__ import annotations

import torch
from torch import nn

from mehs.ssr.net.base import NetConfig, SSRNetwork
from mehs.ssr.net.basis import MexicanHatBranch, SigmoidBasisBranch
from mehs.ssr.net.layers import FCDenseNet
from mehs.ssr.net import fcdensenet_lean
from mehs.ssr.net.strips import _plain, training_graph

#: Jégou et al.'s FC-DenseNet56: 48 first filters, 5 levels of 4 layers, bottleneck 4,
#: growth 12 (published: 1.5 M parameters with a 1×1 classifier).
FC_DENSENET56 = dict(first_channels=48, down_layers=(4, 4, 4, 4, 4), bottleneck_layers=4,
                     growth=12, reduction=4)
#: A 3-level FC-DenseNet that trains on two CPU cores in minutes.
FC_DENSENET_SMALL = dict(first_channels=16, down_layers=(2, 2, 2), bottleneck_layers=2,
                         growth=8, reduction=4)
#: Smallest sensible net (unit tests).
FC_DENSENET_TINY = dict(first_channels=8, down_layers=(1, 1), bottleneck_layers=1, growth=8,
                        reduction=4)

_FEATURE_KEYS = ("first_channels", "down_layers", "bottleneck_layers", "growth", "reduction",
                 "attention", "dropout")


def fcdensenet_from_params(p: dict) -> FCDenseNet:
    """An RGB :class:`FCDenseNet` from a preset/params dict (extra keys ignored)."""
    kw = {k: p[k] for k in _FEATURE_KEYS if k in p}
    kw["down_layers"] = tuple(int(n) for n in kw.get("down_layers", (2, 2, 2)))
    return FCDenseNet(3, **kw)


class TwoBranchFCDenseNet(SSRNetwork):
    """FC-DenseNet + sigmoid and Mexican-hat basis branches + 1×1 fusion conv.

    Parameters (``params``): the FC-DenseNet sizes (``first_channels``,
    ``down_layers``, ``bottleneck_layers``, ``growth``), ``attention`` / ``dropout``
    / ``reduction`` of the dense layers, ``n_basis`` per branch.
    """

    PRESETS = {
        "full": dict(FC_DENSENET56, attention=False, dropout=0.2, n_basis=10),
        "small": dict(FC_DENSENET_SMALL, attention=False, dropout=0.2, n_basis=10),
        "tiny": dict(FC_DENSENET_TINY, attention=False, dropout=0.2, n_basis=10),
    }

    #: Pixels per row strip of the head at inference (0: the whole map at once).
    chunk_pixels: int = 32768

    def __init__(self, config: NetConfig, **p):
        super().__init__(config)
        self.features = fcdensenet_from_params(p)
        c = self.features.out_channels
        n_basis = int(p.get("n_basis", 10))
        self.sigmoid_branch = SigmoidBasisBranch(c, config.wavelengths, n_basis)
        self.hat_branch = MexicanHatBranch(c, config.wavelengths, n_basis)
        self.fusion = nn.Conv2d(2 * self.n_bands, self.n_bands, kernel_size=1)

    def body(self, x: torch.Tensor) -> torch.Tensor:
        # (with a subclass or a forward hook on a part, that part sees, and may replace,
        # one whole-map call)
        if training_graph() or not (_plain(self.sigmoid_branch, SigmoidBasisBranch)
                                    and _plain(self.hat_branch, MexicanHatBranch)
                                    and _plain(self.fusion, nn.Conv2d)
                                    and self.fusion.kernel_size == (1, 1)
                                    and self.fusion.stride == (1, 1)
                                    and self.fusion.padding == (0, 0)):
            f = self.features(x)
            return self.fusion(torch.cat([self.sigmoid_branch(f), self.hat_branch(f)], dim=1))
        # inference: the head is per pixel, so it runs in row strips of about
        # chunk_pixels pixels (the branches' own strips) straight into the output; the
        # features are read a strip at a time, never concatenated (the branches' outputs
        # side by side and the fusion's were 62 more channels at the head's peak, and
        # the features one 192-channel map, issue 16)
        L = self.n_bands
        both_memory = []        # (one block for every strip's branch outputs)

        def strip(part: torch.Tensor) -> torch.Tensor:
            n, _, r, w = part.shape
            if not both_memory or both_memory[0].numel() < n * 2 * L * r * w:
                both_memory[:] = [part.new_empty(n * 2 * L * r * w)]
            both = both_memory[0][:n * 2 * L * r * w].view(n, 2 * L, r, w)
            self.sigmoid_branch(part, out=both[:, :L])
            self.hat_branch(part, out=both[:, L:])
            return self.fusion(both)

        return fcdensenet_lean.head(self.features, x, L, self.chunk_pixels, strip)


class MikamotoTwoBranch(TwoBranchFCDenseNet):
    """Mikamoto et al.'s two-branch network (sigmoid + Mexican hat), no attention:
    dense layers BN → ReLU → 3×3 conv → dropout(0.2) as in Jégou et al."""
