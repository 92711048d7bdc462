"""What every SSR network of the zoo shares: its configuration, input pre-processing,
the two learning modes and their losses, luminance restoration in torch.

A network is ``forward(rgb (N, 3, H, W) linear float32) -> (N, L, H, W)``; what the
``L`` channels mean depends on the **learning mode**, which is independent of the
architecture (the paper trains its own net and Galliani's both ways, Table 1):

- ``"similarity"`` (◇, Sakamoto et al.'s chrominance decomposition, the paper's
  default): the output is the *standard spectrum* ``S``; the loss is the MSE between
  ``S`` and ``GT / (X+Y+Z)(GT)``; the spectra are ``HS = (X+Y+Z)_rgb / (X+Y+Z)_S · S``.
- ``"e2e"``: the output is the spectrum itself; the loss is the MSE on the spectra;
  nothing is restored.

Pre-processing (paper §3.1): Reinhard ``y = x/s / (1 + x/s)`` with a fixed scale
``s`` (``reinhard_scale``, default 1: the data's own unit, as the paper writes
``x/(1+x)``), switchable. The input the network was trained on (HDR or LDR) and the
pre-processing are recorded in :class:`NetConfig` and so in every checkpoint.

XYZ uses the toolkit's one colour-matching matrix :func:`mehs.rgb.cmfs_matrix`
(``k = 1/Σȳ``), held as a buffer, so targets and restoration agree with the
pseudo-RGB images and with :func:`mehs.ssr.luminance.restore_luminance`.

References
----------
- Sakamoto et al., luminance/chrominance decomposition for SSR (reference [14] of
  the HDR SSR paper; learning spectral similarity, restoring with X+Y+Z).
- Reinhard, E., Stark, M., Shirley, P., Ferwerda, J. (2002). Photographic tone
  reproduction for digital images. SIGGRAPH (the ``x/(1+x)`` operator).
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field
from typing import Any

import numpy as np
import torch
from torch import nn

from mehs.errors import InputError
from mehs.rgb import WAVELENGTHS_31, XYZ_TO_SRGB, cmfs_matrix

#: (X+Y+Z) below this is treated as "no signal": excluded from the loss, output 0.
XYZ_SUM_EPS = 1e-8

#: The two learning modes (see the module docstring).
LEARNING_MODES = ("similarity", "e2e")

#: Inputs a network can be trained on.
TRAINED_INPUTS = ("hdr", "ldr")


@dataclass
class NetConfig:
    """Architecture, preset, learning mode and trained input of one network.

    Stored in every checkpoint, so a checkpoint says what it is and what it expects.

    Attributes
    ----------
    arch
        Name in :data:`mehs.ssr.net.zoo.ARCHITECTURES`.
    preset
        ``"full"`` (the published size) or ``"small"`` (trains on two CPU cores).
    mode
        Learning mode, one of :data:`LEARNING_MODES`.
    wavelengths
        Output bands in nm.
    reinhard, reinhard_scale
        Reinhard pre-processing on/off and its scale ``s`` (``x/s / (1 + x/s)``).
    input
        What it was trained on: ``"hdr"`` (pseudo-HDR-RGB) or ``"ldr"``.
    params
        Overrides of the preset's architecture parameters (e.g. ``{"growth": 4}``).
    """

    arch: str = "hdrssr"
    preset: str = "small"
    mode: str = "similarity"
    wavelengths: list[float] = field(default_factory=lambda: WAVELENGTHS_31.tolist())
    reinhard: bool = True
    reinhard_scale: float = 1.0
    input: str = "hdr"
    params: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self):
        if self.mode not in LEARNING_MODES:
            raise InputError(f"learning mode must be one of {LEARNING_MODES}, got {self.mode!r}")
        if self.input not in TRAINED_INPUTS:
            raise InputError(f"trained input must be one of {TRAINED_INPUTS}, got {self.input!r}")
        s = float(self.reinhard_scale)
        if not (math.isfinite(s) and s > 0):
            raise InputError(f"reinhard_scale must be a positive number, got {self.reinhard_scale}")
        self.reinhard_scale = s
        self.reinhard = bool(self.reinhard)
        self.params = dict(self.params or {})

    @property
    def variant(self) -> str:
        """Short label: the architecture, with ``-e2e`` for end-to-end learning."""
        return self.arch if self.mode == "similarity" else f"{self.arch}-e2e"

    @property
    def preprocessing(self) -> str | None:
        """``"reinhard"`` or ``None`` (what the network applies to its input itself)."""
        return "reinhard" if self.reinhard else None

    def to_dict(self) -> dict[str, Any]:
        d = asdict(self)
        d["params"] = {k: list(v) if isinstance(v, tuple) else v for k, v in self.params.items()}
        d["variant"] = self.variant  # read by older tools; ignored when read back
        return d

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> "NetConfig":
        """Inverse of :meth:`to_dict`; also reads the single-architecture configuration
        of checkpoint format 1 (``variant`` ``hdrssr``/``fcdensenet`` + FC-DenseNet sizes)."""
        d = dict(d)
        if "arch" not in d and "variant" in d:
            d = _legacy_to_current(d)
        known = {k: v for k, v in d.items() if k in cls.__dataclass_fields__}
        return cls(**known)


#: FC-DenseNet size fields of checkpoint format 1 and the legacy ``build_network`` keywords.
LEGACY_FCDENSENET_KEYS = ("first_channels", "down_layers", "bottleneck_layers", "growth",
                          "reduction", "n_basis")


def _legacy_to_current(d: dict[str, Any]) -> dict[str, Any]:
    """Format-1 config → current: ``hdrssr`` stays; ``fcdensenet`` (FC-DenseNet with
    channel attention, end to end) is the Galliani FC-DenseNet with attention in place
    of dropout, learning end to end. Layer names are unchanged, so weights load."""
    d = dict(d)
    variant = d.pop("variant")
    params = dict(d.pop("params", {}) or {})
    for k in LEGACY_FCDENSENET_KEYS:
        if k in d:
            params[k] = d.pop(k)
    if variant == "hdrssr":
        d.update(arch="hdrssr", mode="similarity")
    elif variant == "fcdensenet":
        params.pop("n_basis", None)
        params.update(attention=True, dropout=0.0)
        d.update(arch="galliani", mode="e2e")
    else:
        raise InputError(f"unknown network variant {variant!r}; choose one of "
                         "['fcdensenet', 'hdrssr'] (or name an architecture with arch=)")
    d.setdefault("preset", "small")
    d["params"] = params
    return d


def reinhard_torch(x: torch.Tensor, scale: float = 1.0) -> torch.Tensor:
    """Reinhard ``y / (1 + y)``, ``y = max(x, 0) / scale`` (same as
    :func:`mehs.ssr.preprocess.reinhard` for ``scale = 1``)."""
    y = torch.clamp(x, min=0.0)
    if scale != 1.0:
        y = y / scale
    return y / (1.0 + y)


def masked_mse(pred: torch.Tensor, target: torch.Tensor, valid: torch.Tensor) -> torch.Tensor:
    """MSE over valid pixels × bands; ``valid`` is ``(N, 1, H, W)`` bool."""
    w = valid.to(pred.dtype)
    n = w.sum() * pred.shape[1]
    return ((pred - target) ** 2 * w).sum() / torch.clamp(n, min=1.0)


def masked_mrae(pred: torch.Tensor, target: torch.Tensor, valid: torch.Tensor) -> torch.Tensor:
    """Mean relative absolute error ``|ŷ − y| / y`` over valid elements with ``y > 0``
    (NTIRE's MRAE, MST++'s ``Loss_MRAE``, without its division by a zero target)."""
    pos = (target > 0) & valid
    w = pos.to(pred.dtype)
    rel = (pred - target).abs() / torch.where(pos, target, torch.ones_like(target))
    return (rel * w).sum() / torch.clamp(w.sum(), min=1.0)


#: Training losses by name (``TrainConfig.loss``).
LOSSES = {"mse": masked_mse, "mrae": masked_mrae}


class SSRNetwork(nn.Module):
    """Base of every zoo network. Subclasses build their layers in ``__init__`` (after
    calling ``super().__init__(config)``) and implement :meth:`body`
    ``(N, 3, H, W) -> (N, L, H, W)``, which sees the pre-processed input.

    Class attributes: ``receptive_radius`` — pixels of context one output pixel
    depends on when the network is purely local (then tiled inference with that
    much overlap is exact, :func:`mehs.ssr.net.infer.predict_tiled`), ``None`` when
    it has image-wide operations (global pooling, attention over all pixels). The
    models' own tiling (:mod:`mehs.ssr.tiling`) measures the field instead of reading
    it: a declaration goes stale when a part is replaced.
    """

    receptive_radius: int | None = None

    def __init__(self, config: NetConfig):
        super().__init__()
        self.config = config
        wl = np.asarray(config.wavelengths, dtype=np.float64)
        if wl.ndim != 1 or wl.size < 2:
            raise InputError(f"a network needs at least 2 output wavelengths, got {wl.size}")
        self.n_bands = int(wl.size)
        # (X+Y+Z)(S) = S · Σ_c M[:, c]; only the row sums of the CMF matrix are needed.
        cmfs = torch.as_tensor(cmfs_matrix(wl), dtype=torch.float32)
        self.register_buffer("xyz_sum_weights", cmfs.sum(dim=1), persistent=False)
        rgb_to_xyz = torch.as_tensor(np.linalg.inv(XYZ_TO_SRGB), dtype=torch.float32)
        self.register_buffer("rgb_xyz_sum_weights", rgb_to_xyz.sum(dim=0), persistent=False)

    # -- what the checkpoint declares ---------------------------------------------------
    @property
    def wavelengths(self) -> np.ndarray:
        return np.asarray(self.config.wavelengths, dtype=np.float64)

    @property
    def predicts_standard_spectrum(self) -> bool:
        """True in ``similarity`` mode: the output needs luminance restoration."""
        return self.config.mode == "similarity"

    def trained_input(self) -> dict[str, Any]:
        """The setting the network was trained for (what an evaluation must feed it)."""
        c = self.config
        return {"arch": c.arch, "preset": c.preset, "mode": c.mode, "input": c.input,
                "preprocessing": c.preprocessing, "reinhard_scale": c.reinhard_scale,
                "restores_luminance": self.predicts_standard_spectrum}

    # -- forward -------------------------------------------------------------------------
    def preprocess(self, rgb: torch.Tensor) -> torch.Tensor:
        return reinhard_torch(rgb, self.config.reinhard_scale) if self.config.reinhard else rgb

    def body(self, x: torch.Tensor) -> torch.Tensor:  # pragma: no cover - abstract
        raise NotImplementedError

    def forward(self, rgb: torch.Tensor) -> torch.Tensor:
        """Linear RGB ``(N, 3, H, W)`` → ``S`` (similarity) or spectra (e2e) ``(N, L, H, W)``."""
        return self.body(self.preprocess(rgb))

    # -- XYZ and luminance ---------------------------------------------------------------
    def xyz_sum(self, spectra: torch.Tensor) -> torch.Tensor:
        """``(X+Y+Z)`` of spectra ``(N, L, H, W)`` → ``(N, 1, H, W)``."""
        return torch.einsum("nlhw,l->nhw", spectra, self.xyz_sum_weights).unsqueeze(1)

    def rgb_xyz_sum(self, rgb: torch.Tensor) -> torch.Tensor:
        """``(X+Y+Z)`` of linear sRGB ``(N, 3, H, W)`` → ``(N, 1, H, W)``."""
        return torch.einsum("nchw,c->nhw", rgb, self.rgb_xyz_sum_weights).unsqueeze(1)

    def restore_luminance(self, S: torch.Tensor, rgb: torch.Tensor) -> torch.Tensor:
        """``HS = (X+Y+Z)_rgb / (X+Y+Z)_S · S``: a torch copy of
        :func:`mehs.ssr.luminance.restore_luminance` for exported graphs, with the
        same guard (a shape whose ``X+Y+Z`` is not positive becomes a flat spectrum
        carrying the input's ``X+Y+Z``)."""
        have = self.xyz_sum(S)
        target = self.rgb_xyz_sum(rgb)
        # the numpy guard exactly: X+Y+Z > 0 (not > 1e-8: a dim but valid shape kept its
        # form there and went flat here, 46° apart), and a finite result
        good = (have > 0) & torch.isfinite(have)
        factor = target / torch.where(good, have, torch.ones_like(have))
        out = S * factor
        good = good & torch.isfinite(out).all(dim=1, keepdim=True)
        flat = (target / self.xyz_sum_weights.sum()).expand_as(S)
        return torch.where(good, out, flat)

    def spectra(self, rgb: torch.Tensor) -> torch.Tensor:
        """Full conversion linear RGB ``(N, 3, H, W)`` → spectra ``(N, L, H, W)``."""
        out = self(rgb)
        if self.predicts_standard_spectrum:
            out = self.restore_luminance(out, rgb)
        return out

    # -- losses --------------------------------------------------------------------------
    def target(self, hs: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """What the output is compared with, and where: ``GT/(X+Y+Z)(GT)`` and the pixels
        with signal (similarity), or ``GT`` everywhere (e2e)."""
        if not self.predicts_standard_spectrum:
            return hs, torch.ones_like(hs[:, :1], dtype=torch.bool)
        s = self.xyz_sum(hs)
        ok = s > XYZ_SUM_EPS
        return hs / torch.where(ok, s, torch.ones_like(s)), ok

    def loss(self, pred: torch.Tensor, hs: torch.Tensor,
             valid: torch.Tensor | None = None, kind: str = "mse") -> torch.Tensor:
        """The learning mode's loss over valid pixels (``valid`` ``(N, 1, H, W)`` bool):
        ``kind`` ``"mse"`` (default; the paper's end-to-end loss, §4.1) or ``"mrae"``
        (NTIRE / MST++'s training loss)."""
        if kind not in LOSSES:
            raise InputError(f"unknown loss {kind!r}; use one of {', '.join(LOSSES)}")
        target, ok = self.target(hs)
        if valid is not None:
            ok = ok & valid
        return LOSSES[kind](pred, target, ok)


def count_parameters(module: nn.Module) -> int:
    """Number of trainable parameters."""
    return int(sum(p.numel() for p in module.parameters() if p.requires_grad))
