"""Galliani et al. 2017: spectral super-resolution with the FC-DenseNet ("Tiramisu")
of Jégou et al. — dense layers with dropout (p = 0.2), no attention, a 1×1 conv to the
output bands.

``body(x (N, 3, H, W)) -> (N, L, H, W)``. Galliani et al. trained it end to end
(Euclidean loss); the HDR SSR paper trains it both ways (Table 1: ◇ and e2e).

References
----------
- Galliani, S., Lanaras, C., Marmanis, D., Baltsavias, E., Schindler, K. (2017).
  Learned Spectral Super-Resolution. arXiv:1703.09470.
- Jégou, S., Drozdzal, M., Vazquez, D., Romero, A., Bengio, Y. (2017). The One
  Hundred Layers Tiramisu: Fully Convolutional DenseNets for Semantic Segmentation.
  CVPR Workshops (FC-DenseNet56: 1.5 M parameters).
"""

from __future__ import annotations

import torch
from torch import nn
import torch.nn.functional as F

from mehs.ssr.net.base import NetConfig, SSRNetwork
from mehs.ssr.net import fcdensenet_lean
from mehs.ssr.net.strips import STRIP_PIXELS, _plain, conv2d_into, training_graph
from mehs.ssr.net.mikamoto import (FC_DENSENET56, FC_DENSENET_SMALL, FC_DENSENET_TINY,
                                   fcdensenet_from_params)


class Galliani2017(SSRNetwork):
    """FC-DenseNet56 (48 first filters, 5 levels × 4 layers, bottleneck 4, growth 12,
    dropout 0.2) with a 1×1 conv head. ``attention=True, dropout=0`` gives the
    attention variant that checkpoint format 1 called ``fcdensenet``."""

    PRESETS = {
        "full": dict(FC_DENSENET56, attention=False, dropout=0.2),
        "small": dict(FC_DENSENET_SMALL, attention=False, dropout=0.2),
        "tiny": dict(FC_DENSENET_TINY, attention=False, dropout=0.2),
    }

    def __init__(self, config: NetConfig, **p):
        super().__init__(config)
        self.features = fcdensenet_from_params(p)
        self.head = nn.Conv2d(self.features.out_channels, self.n_bands, kernel_size=1)

    #: Pixels per row strip of the head at inference (0: the whole map at once).
    chunk_pixels: int = STRIP_PIXELS

    def body(self, x: torch.Tensor) -> torch.Tensor:
        head = self.head
        if training_graph():
            return head(self.features(x))
        if not (_plain(head, nn.Conv2d) and head.kernel_size == (1, 1) and head.stride == (1, 1)
                and head.padding == (0, 0) and head.dilation == (1, 1)):
            # (a replaced or hooked head sees the cropped features, in one call)
            return conv2d_into(head, self.features(x), chunk_pixels=self.chunk_pixels)
        # inference: a whole-map 1×1 convolution held a reordered copy of the 192
        # feature channels (4.3 GB resident for FC-DenseNet56 at 2048×1024, issue 16);
        # in strips it reads the features a strip at a time, never concatenated

        def strip(part: torch.Tensor) -> torch.Tensor:
            return F.conv2d(part, head.weight, head.bias, groups=head.groups)

        return fcdensenet_lean.head(self.features, x, head.out_channels, self.chunk_pixels,
                                    strip)
