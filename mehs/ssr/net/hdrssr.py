"""The HDR SSR paper's network: Mikamoto's two-branch network (sigmoid and Mexican-hat
basis branches, fusion) on an FC-DenseNet whose dense layers carry channel attention
(Zhang et al. 2018, r = 4) in place of dropout (paper §3.2, Fig. 3–6).

``body(x (N, 3, H, W)) -> (N, L, H, W)``; in the paper's learning mode (similarity)
the output is the standard spectrum ``S`` and the luminance is restored afterwards.

References
----------
- Spectral Super-Resolution for High Dynamic Range Images (the source paper), §3.2.
- Zhang, Y. et al. (2018). Image super-resolution using very deep residual channel
  attention networks. ECCV (the channel attention).
- Mikamoto et al., see :mod:`mehs.ssr.net.mikamoto`.
"""

from __future__ import annotations

from mehs.ssr.net.mikamoto import (FC_DENSENET56, FC_DENSENET_SMALL, FC_DENSENET_TINY,
                                   TwoBranchFCDenseNet)


class HDRSSR(TwoBranchFCDenseNet):
    """Two-branch FC-DenseNet with channel attention (r = 4) in every dense layer, no dropout.

    The paper does not give its FC-DenseNet's size; the full preset uses the same
    FC-DenseNet56 as the Galliani and Mikamoto presets, so the three differ only in
    what the paper changes (attention vs dropout; basis branches vs a 1×1 head).
    """

    PRESETS = {
        "full": dict(FC_DENSENET56, attention=True, reduction=4, dropout=0.0, n_basis=10),
        "small": dict(FC_DENSENET_SMALL, attention=True, reduction=4, dropout=0.0, n_basis=10),
        "tiny": dict(FC_DENSENET_TINY, attention=True, reduction=4, dropout=0.0, n_basis=10),
    }
