"""Compatibility names for code written against checkpoint format 1.

The networks now live one per module (:mod:`~mehs.ssr.net.hdrssr`,
:mod:`~mehs.ssr.net.galliani2017`, …) with their shared base in
:mod:`~mehs.ssr.net.base` and the builder in :mod:`~mehs.ssr.net.zoo`.
``HDRSSRNet`` is the paper's network; ``FCDenseNetSSR`` the Galliani FC-DenseNet.
"""

from __future__ import annotations

from mehs.ssr.net.base import (XYZ_SUM_EPS, NetConfig, SSRNetwork, masked_mse,  # noqa: F401
                               reinhard_torch)
from mehs.ssr.net.galliani2017 import Galliani2017 as FCDenseNetSSR  # noqa: F401
from mehs.ssr.net.hdrssr import HDRSSR as HDRSSRNet  # noqa: F401
from mehs.ssr.net.zoo import ARCHITECTURES, build_network  # noqa: F401

#: Architectures by name (the zoo's dispatcher dict).
VARIANTS = ARCHITECTURES
