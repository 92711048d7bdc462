"""The two network variants, their configuration and their losses.

- :class:`HDRSSRNet` (``"hdrssr"``): FC-DenseNet features → sigmoid-basis and
  Mexican-hat-basis branches → 1×1 fusion conv → the *standard spectrum*
  ``S`` (31 bands). It learns spectral similarity only: the loss compares ``S``
  with ``GT / (X+Y+Z)(GT)`` (chrominance decomposition); the luminance is put
  back afterwards, ``HS = (X+Y+Z)_rgb / (X+Y+Z)_S · S``.
- :class:`FCDenseNetSSR` (``"fcdensenet"``): the same feature extractor and a
  1×1 conv straight to the spectra, trained end to end with MSE on the spectra.

Both take linear RGB ``(N, 3, H, W)`` float32 and apply Reinhard ``x/(1+x)``
to it first when ``config.reinhard`` is true. XYZ uses the toolkit's one
colour-matching matrix :func:`mehs.rgb.cmfs_matrix` (``k = 1/Σȳ``), held as a
buffer, so training targets and luminance restoration agree with the
pseudo-RGB images and with :func:`mehs.ssr.luminance.restore_luminance`.

References
----------
- Jégou et al. 2017; Galliani et al. 2017 (FC-DenseNet for SSR).
- Jakob & Hanika 2019 (sigmoid basis).
- Reinhard, E., Stark, M., Shirley, P., Ferwerda, J. (2002). Photographic tone
  reproduction for digital images. SIGGRAPH (the ``x/(1+x)`` operator).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field
from typing import Any

import numpy as np
import torch
from torch import nn

from mehs.errors import InputError
from mehs.rgb import WAVELENGTHS_31, XYZ_TO_SRGB, cmfs_matrix
from mehs.ssr.net.basis import MexicanHatBranch, SigmoidBasisBranch
from mehs.ssr.net.layers import FCDenseNet

#: (X+Y+Z) below this is treated as "no signal": excluded from the loss, output 0.
XYZ_SUM_EPS = 1e-8


@dataclass
class NetConfig:
    """Architecture and pre-processing of one network (stored in every checkpoint).

    The defaults are a small net (≈ 60 k parameters) that trains on a CPU; the
    paper's net is larger (e.g. ``first_channels=48, down_layers=(4, 5, 7),
    bottleneck_layers=10, growth=16``).
    """

    variant: str = "hdrssr"
    wavelengths: list[float] = field(default_factory=lambda: WAVELENGTHS_31.tolist())
    first_channels: int = 16
    down_layers: tuple[int, ...] = (2, 2, 2)
    bottleneck_layers: int = 2
    growth: int = 8
    reduction: int = 4
    n_basis: int = 10
    reinhard: bool = True

    def __post_init__(self):
        # torch would fail later with "negative dimension" (or build an empty layer)
        for name in ("first_channels", "bottleneck_layers", "growth", "reduction", "n_basis"):
            if int(getattr(self, name)) < 1:
                raise InputError(f"network {name} must be at least 1, got {getattr(self, name)}")
        if not self.down_layers or any(int(n) < 1 for n in self.down_layers):
            raise InputError(f"network down_layers must be positive counts, got {self.down_layers}")

    def to_dict(self) -> dict[str, Any]:
        d = asdict(self)
        d["down_layers"] = list(self.down_layers)
        return d

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> "NetConfig":
        known = {k: v for k, v in d.items() if k in cls.__dataclass_fields__}
        if "down_layers" in known:
            known["down_layers"] = tuple(int(n) for n in known["down_layers"])
        return cls(**known)


def reinhard_torch(x: torch.Tensor) -> torch.Tensor:
    """Reinhard ``x / (1 + x)`` (same as :func:`mehs.ssr.preprocess.reinhard`); negatives clipped."""
    x = torch.clamp(x, min=0.0)
    return x / (1.0 + x)


class _SSRBase(nn.Module):
    """Shared pieces: configuration, XYZ buffers, luminance restoration in torch."""

    predicts_standard_spectrum = False

    def __init__(self, config: NetConfig):
        super().__init__()
        self.config = config
        wl = np.asarray(config.wavelengths, dtype=np.float64)
        if wl.ndim != 1 or wl.size < 2:
            raise InputError(f"a network needs at least 2 output wavelengths, got {wl.size}")
        self.n_bands = wl.size
        # (X+Y+Z)(S) = S · Σ_c M[:, c]; only the row sums of the CMF matrix are needed.
        cmfs = torch.as_tensor(cmfs_matrix(wl), dtype=torch.float32)
        self.register_buffer("xyz_sum_weights", cmfs.sum(dim=1), persistent=False)
        rgb_to_xyz = torch.as_tensor(np.linalg.inv(XYZ_TO_SRGB), dtype=torch.float32)
        self.register_buffer("rgb_xyz_sum_weights", rgb_to_xyz.sum(dim=0), persistent=False)
        self.features = FCDenseNet(3, first_channels=config.first_channels,
                                   down_layers=config.down_layers,
                                   bottleneck_layers=config.bottleneck_layers,
                                   growth=config.growth, reduction=config.reduction)

    @property
    def wavelengths(self) -> np.ndarray:
        return np.asarray(self.config.wavelengths, dtype=np.float64)

    def preprocess(self, rgb: torch.Tensor) -> torch.Tensor:
        return reinhard_torch(rgb) if self.config.reinhard else rgb

    def xyz_sum(self, spectra: torch.Tensor) -> torch.Tensor:
        """``(X+Y+Z)`` of spectra ``(N, L, H, W)`` → ``(N, 1, H, W)``."""
        return torch.einsum("nlhw,l->nhw", spectra, self.xyz_sum_weights).unsqueeze(1)

    def rgb_xyz_sum(self, rgb: torch.Tensor) -> torch.Tensor:
        """``(X+Y+Z)`` of linear sRGB ``(N, 3, H, W)`` → ``(N, 1, H, W)``."""
        return torch.einsum("nchw,c->nhw", rgb, self.rgb_xyz_sum_weights).unsqueeze(1)

    def restore_luminance(self, S: torch.Tensor, rgb: torch.Tensor) -> torch.Tensor:
        """``HS = (X+Y+Z)_rgb / (X+Y+Z)_S · S``: a torch copy of
        :func:`mehs.ssr.luminance.restore_luminance` for the exported graph, with the
        same guard (a shape whose ``X+Y+Z`` is not positive becomes a flat spectrum
        carrying the input's ``X+Y+Z``)."""
        have = self.xyz_sum(S)
        target = self.rgb_xyz_sum(rgb)
        good = have > XYZ_SUM_EPS
        factor = target / torch.where(good, have, torch.ones_like(have))
        flat = (target / self.xyz_sum_weights.sum()).expand_as(S)
        return torch.where(good, S * factor, flat)

    def spectra(self, rgb: torch.Tensor) -> torch.Tensor:
        """Full conversion linear RGB ``(N, 3, H, W)`` → spectra ``(N, L, H, W)``."""
        out = self(rgb)
        if self.predicts_standard_spectrum:
            out = self.restore_luminance(out, rgb)
        return out

    def loss(self, pred: torch.Tensor, hs: torch.Tensor,
             valid: torch.Tensor | None = None) -> torch.Tensor:  # pragma: no cover
        raise NotImplementedError


def _masked_mse(pred: torch.Tensor, target: torch.Tensor, valid: torch.Tensor) -> torch.Tensor:
    # valid: (N, 1, H, W) bool; the mean is over valid pixels × bands.
    w = valid.to(pred.dtype)
    n = w.sum() * pred.shape[1]
    return ((pred - target) ** 2 * w).sum() / torch.clamp(n, min=1.0)


class HDRSSRNet(_SSRBase):
    """FC-DenseNet + sigmoid and Mexican-hat basis branches + fusion → standard spectrum ``S``.

    ``forward(rgb (N,3,H,W)) -> S (N,L,H,W)``; :meth:`spectra` adds the luminance.
    """

    predicts_standard_spectrum = True

    def __init__(self, config: NetConfig | None = None):
        config = config or NetConfig(variant="hdrssr")
        super().__init__(config)
        c = self.features.out_channels
        self.sigmoid_branch = SigmoidBasisBranch(c, config.wavelengths, config.n_basis)
        self.hat_branch = MexicanHatBranch(c, config.wavelengths, config.n_basis)
        self.fusion = nn.Conv2d(2 * self.n_bands, self.n_bands, kernel_size=1)

    def forward(self, rgb: torch.Tensor) -> torch.Tensor:
        f = self.features(self.preprocess(rgb))
        return self.fusion(torch.cat([self.sigmoid_branch(f), self.hat_branch(f)], dim=1))

    def target(self, hs: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Chrominance target ``GT / (X+Y+Z)(GT)`` and the mask of pixels where it exists."""
        s = self.xyz_sum(hs)
        ok = s > XYZ_SUM_EPS
        return hs / torch.where(ok, s, torch.ones_like(s)), ok

    def loss(self, pred, hs, valid=None):
        """MSE between predicted ``S`` and ``GT/(X+Y+Z)`` over valid pixels with signal."""
        target, ok = self.target(hs)
        if valid is not None:
            ok = ok & valid
        return _masked_mse(pred, target, ok)


class FCDenseNetSSR(_SSRBase):
    """Plain FC-DenseNet, end to end: ``forward(rgb) -> HS (N,L,H,W)``, MSE on the spectra."""

    def __init__(self, config: NetConfig | None = None):
        config = config or NetConfig(variant="fcdensenet")
        super().__init__(config)
        self.head = nn.Conv2d(self.features.out_channels, self.n_bands, kernel_size=1)

    def forward(self, rgb: torch.Tensor) -> torch.Tensor:
        return self.head(self.features(self.preprocess(rgb)))

    def loss(self, pred, hs, valid=None):
        if valid is None:
            valid = torch.ones_like(hs[:, :1], dtype=torch.bool)
        return _masked_mse(pred, hs, valid)


#: Network variants by name.
VARIANTS = {"hdrssr": HDRSSRNet, "fcdensenet": FCDenseNetSSR}


def build_network(config: NetConfig | dict | None = None, **overrides) -> _SSRBase:
    """Build a network from a :class:`NetConfig` (or its dict form) with field overrides."""
    if config is None:
        config = NetConfig()
    elif isinstance(config, dict):
        config = NetConfig.from_dict(config)
    if overrides:
        config = NetConfig.from_dict({**config.to_dict(), **overrides})
    try:
        cls = VARIANTS[config.variant]
    except KeyError:
        raise InputError(f"unknown network variant {config.variant!r}; "
                         f"choose one of {sorted(VARIANTS)}") from None
    return cls(config)
