"""The HDR SSR network (PyTorch, optional extra ``mehs[torch]``).

An FC-DenseNet feature extractor whose dense layers use channel attention in
place of dropout, followed by two basis-function branches (sigmoid and
Mexican hat) and a fusion layer that predicts the *standard spectrum*
``S = HS / (X+Y+Z)`` of every pixel; the luminance is restored afterwards with
:func:`mehs.ssr.luminance.restore_luminance`. The plain end-to-end FC-DenseNet
(MSE on the spectra) is the comparison variant.

Modules: :mod:`~mehs.ssr.net.layers` (dense blocks, channel attention,
FC-DenseNet), :mod:`~mehs.ssr.net.basis` (basis functions and branches),
:mod:`~mehs.ssr.net.model` (the two variants, losses, configuration),
:mod:`~mehs.ssr.net.train` (training loop, checkpoints),
:mod:`~mehs.ssr.net.export` (model-contract wrapper, ONNX export),
:mod:`~mehs.ssr.net.register` (registers ``hdrssr`` and ``fcdensenet``).

Importing this package needs torch; the rest of mehs does not.
"""

from __future__ import annotations

try:
    import torch  # noqa: F401
except ImportError as exc:  # pragma: no cover - depends on the environment
    raise ImportError(
        "mehs.ssr.net needs PyTorch: install the extra with "
        "`pip install \"mehs[torch]\"` (torch==2.13.0)") from exc

from mehs.ssr.net.basis import (BASIS_FUNCTIONS, MexicanHatBranch, SigmoidBasisBranch,  # noqa: E402
                                mexican_hat_basis, normalise_wavelengths, sigmoid_basis,
                                sigmoid_Jakob2019)
from mehs.ssr.net.layers import ChannelAttention, DenseLayer, FCDenseNet  # noqa: E402
from mehs.ssr.net.model import (VARIANTS, FCDenseNetSSR, HDRSSRNet, NetConfig,  # noqa: E402
                                build_network)

__all__ = [
    "BASIS_FUNCTIONS", "ChannelAttention", "DenseLayer", "FCDenseNet", "FCDenseNetSSR",
    "HDRSSRNet", "MexicanHatBranch", "NetConfig", "SigmoidBasisBranch", "VARIANTS",
    "build_network", "mexican_hat_basis", "normalise_wavelengths", "sigmoid_Jakob2019",
    "sigmoid_basis",
]
