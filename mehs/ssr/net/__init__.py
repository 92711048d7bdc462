"""The SSR network zoo (PyTorch, optional extra ``mehs[torch]``).

Every network maps linear RGB ``(N, 3, H, W)`` to ``(N, L, H, W)`` and is trained by
one recipe (:mod:`~mehs.ssr.net.train`) in either learning mode: spectral similarity
(the standard spectrum ``S = HS/(X+Y+Z)``, luminance restored afterwards) or end to
end (MSE on the spectra). Architectures, one module each, all in the dispatcher dict
:data:`~mehs.ssr.net.zoo.ARCHITECTURES`:

- ``hdrssr`` (:mod:`~mehs.ssr.net.hdrssr`): the HDR SSR paper's network;
- ``mikamoto`` (:mod:`~mehs.ssr.net.mikamoto`): Mikamoto's two-branch network;
- ``galliani`` (:mod:`~mehs.ssr.net.galliani2017`): Galliani 2017, FC-DenseNet;
- ``hscnnd`` (:mod:`~mehs.ssr.net.hscnnd2018`): HSCNN-D, Shi 2018;
- ``awan`` (:mod:`~mehs.ssr.net.awan2020`): AWAN, Li 2020;
- ``mstpp`` (:mod:`~mehs.ssr.net.mstpp2022`): MST++, Cai 2022.

Shared pieces: :mod:`~mehs.ssr.net.base` (configuration, learning modes, losses,
luminance restoration), :mod:`~mehs.ssr.net.layers` (FC-DenseNet, channel
attention), :mod:`~mehs.ssr.net.basis` (basis functions and branches),
:mod:`~mehs.ssr.net.infer` (tiled inference), :mod:`~mehs.ssr.net.train` (training
loop, checkpoints), :mod:`~mehs.ssr.net.export` (model-contract wrapper, ONNX).
``python -m mehs.ssr.net`` prints the parameter counts.

Importing this package needs torch; the rest of mehs does not.
"""

from __future__ import annotations

try:
    import torch  # noqa: F401
except ImportError as exc:  # pragma: no cover - depends on the environment
    _NEEDS = ("mehs.ssr.net needs PyTorch: install the extra with "
              "`pip install \"mehs[torch]\"` (torch==2.13.0)")
    import sys

    if sys.argv[:1] == ["-m"]:
        # `python -m mehs.ssr.net` (argv[0] is "-m" while its package is imported): one
        # line for the user, not runpy's traceback
        raise SystemExit(f"{_NEEDS}") from None
    raise ImportError(_NEEDS) from exc

from mehs.ssr.net.base import LEARNING_MODES, NetConfig, SSRNetwork  # noqa: E402
from mehs.ssr.net.basis import (BASIS_FUNCTIONS, MexicanHatBranch, SigmoidBasisBranch,  # noqa: E402
                                mexican_hat_basis, normalise_wavelengths, sigmoid_basis,
                                sigmoid_Jakob2019)
from mehs.ssr.net.layers import ChannelAttention, DenseLayer, FCDenseNet  # noqa: E402
from mehs.ssr.net.model import VARIANTS, FCDenseNetSSR, HDRSSRNet  # noqa: E402
from mehs.ssr.net.zoo import (ARCHITECTURES, build_network, format_parameter_table,  # noqa: E402
                              parameter_table)

__all__ = [
    "ARCHITECTURES", "BASIS_FUNCTIONS", "ChannelAttention", "DenseLayer", "FCDenseNet",
    "FCDenseNetSSR", "HDRSSRNet", "LEARNING_MODES", "MexicanHatBranch", "NetConfig",
    "SSRNetwork", "SigmoidBasisBranch", "VARIANTS", "build_network", "format_parameter_table",
    "mexican_hat_basis", "normalise_wavelengths", "parameter_table", "sigmoid_Jakob2019",
    "sigmoid_basis",
]
