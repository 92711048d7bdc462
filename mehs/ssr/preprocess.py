"""Input pre-processing for SSR models (paper §3.3): Reinhard's global operator.

``f(x) = x / (1 + x)`` maps HDR linear RGB ``[0, ∞)`` into ``[0, 1)`` so that a
model trained on display-range data sees inputs of the range it knows. It is
applied per channel, as in the paper.

The scale at which the operator is applied matters: on data in the camera's
unit (DN/ms, every pixel ≫ 1) ``x/(1+x)`` pushes every channel towards 1 and
changes every pixel's chromaticity. :class:`Preprocessing` therefore records
the scale with the operator, and a model records the one it was trained with:

- ``key`` (default **0.18**, Reinhard et al. 2002, eq. 1–2): each image is
  first multiplied by ``key / L̄w``, where ``L̄w = exp(mean(log(Y)))`` is the
  log-average luminance of its pixels with ``Y > 0`` (``Y`` from linear sRGB,
  Rec. 709 weights). The operator is then independent of the data's unit and
  exposure: ``f(k·rgb) = f(rgb)`` for any ``k > 0``.
- ``key=None``: a fixed ``scale`` (default 1) instead, ``f(scale·x)``;
  ``Preprocessing(key=None, scale=1)`` is the paper's ``x/(1+x)`` on the data as
  given (what the networks of :mod:`mehs.ssr.net` trained with ``reinhard=True``
  use).

References
----------
- Reinhard, E., Stark, M., Shirley, P., Ferwerda, J. (2002). Photographic tone
  reproduction for digital images. ACM Transactions on Graphics 21(3), 267–276.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

#: Largest value :func:`inverse_reinhard` accepts before clipping (its pole is at 1).
INVERSE_CLIP = 1.0 - 1e-6
#: Reinhard et al. 2002's "middle grey" key, the documented default.
DEFAULT_KEY = 0.18
#: Rec. 709 / sRGB luminance weights of linear RGB.
_LUMA = np.array([0.2126, 0.7152, 0.0722])


def reinhard(x: np.ndarray) -> np.ndarray:
    """Reinhard's global operator ``x / (1 + x)``, element-wise.

    Parameters
    ----------
    x
        Linear values, any shape; negatives are clipped to 0 first (the
        operator has a pole at −1 and negative light is not meaningful).

    Returns
    -------
    ndarray
        Same shape, float32 for float32 input (float64 otherwise), in ``[0, 1)``.
    """
    x = np.asarray(x)
    dtype = np.float32 if x.dtype == np.float32 else np.float64
    x = np.maximum(x.astype(dtype, copy=False), 0)
    return x / (1 + x)


def inverse_reinhard(y: np.ndarray, *, clip: float = INVERSE_CLIP) -> np.ndarray:
    """Inverse of :func:`reinhard`: ``y / (1 − y)``.

    ``y`` is clipped to ``[0, clip]`` first, so a model output at or above 1
    (outside the operator's range) maps to the finite value
    ``clip / (1 − clip)`` (≈ 10⁶ by default) instead of ``inf``/NaN.
    """
    y = np.asarray(y)
    dtype = np.float32 if y.dtype == np.float32 else np.float64
    y = np.clip(y.astype(dtype, copy=False), 0, clip)
    return y / (1 - y)


def log_average_luminance(rgb: np.ndarray) -> float:
    """``exp(mean(log Y))`` over the pixels of linear RGB ``(..., 3)`` with finite ``Y > 0``; 1 if none."""
    y = np.asarray(rgb, dtype=np.float64).reshape(-1, 3) @ _LUMA
    y = y[np.isfinite(y) & (y > 0)]
    return float(np.exp(np.mean(np.log(y)))) if y.size else 1.0

#: Dispatcher: pre-processing name → (forward, inverse).
PREPROCESS_METHODS = {
    "reinhard": (reinhard, inverse_reinhard),
}


@dataclass(frozen=True)
class Preprocessing:
    """A recorded pre-processing: operator + the scale it is applied at.

    Attributes
    ----------
    method
        ``"reinhard"`` (the only one so far; see :data:`PREPROCESS_METHODS`).
    key
        Per-image key (log-average luminance → ``key``); ``None`` = fixed ``scale``.
    scale
        Fixed multiplier used when ``key`` is ``None``.
    """

    method: str = "reinhard"
    key: float | None = DEFAULT_KEY
    scale: float = 1.0

    def __post_init__(self):
        if self.method not in PREPROCESS_METHODS:
            raise ValueError(f"unknown pre-processing {self.method!r}; "
                             f"choose one of {sorted(PREPROCESS_METHODS)}")
        if self.key is not None and not (math.isfinite(self.key) and self.key > 0):
            raise ValueError(f"Reinhard key must be a positive number, got {self.key}")
        if not (math.isfinite(self.scale) and self.scale > 0):
            raise ValueError(f"Reinhard scale must be a positive number, got {self.scale}")

    def factor(self, rgb: np.ndarray) -> float:
        """The multiplier applied to ``rgb`` before the operator."""
        return self.key / log_average_luminance(rgb) if self.key is not None else self.scale

    def __call__(self, rgb: np.ndarray) -> np.ndarray:
        """Pre-process linear RGB ``(H, W, 3)`` → same shape, float32 for float32 input."""
        rgb = np.asarray(rgb)
        dtype = np.float32 if rgb.dtype == np.float32 else np.float64
        forward = PREPROCESS_METHODS[self.method][0]
        return forward(rgb.astype(dtype, copy=False) * dtype(self.factor(rgb)))

    def label(self) -> str:
        """Short text for tables and notes, e.g. ``reinhard key 0.18``."""
        return (f"{self.method} key {self.key:g}" if self.key is not None
                else f"{self.method} scale {self.scale:g}")

    def to_dict(self) -> dict[str, Any]:
        return {"method": self.method, "key": self.key, "scale": self.scale}

    @classmethod
    def from_dict(cls, d: Any) -> "Preprocessing | None":
        """Inverse of :meth:`to_dict`; ``None``/``"none"``/``False`` → ``None``;
        ``True``/``"reinhard"`` (older records) → the paper's fixed scale 1."""
        if d is None or d is False or (isinstance(d, str) and d.lower() in ("", "none", "off")):
            return None
        if d is True or (isinstance(d, str) and d.lower() == "reinhard"):
            return cls(key=None, scale=1.0)
        if not isinstance(d, dict):
            raise ValueError(f"not a pre-processing record: {d!r}")
        key, scale = d.get("key", DEFAULT_KEY), d.get("scale", 1.0)

        def number(name: str, v: Any) -> float:
            # float(None) or float([..]) is a TypeError: a broken record must read as one
            try:
                return float(v)
            except (TypeError, ValueError):
                raise ValueError(f"pre-processing record: {name} must be a number, "
                                 f"got {v!r}") from None

        return cls(method=str(d.get("method", "reinhard")),
                   key=None if key is None else number("key", key),
                   scale=1.0 if scale is None and key is not None else number("scale", scale))


#: The paper's own operator: ``x/(1+x)`` on the data as given.
PAPER_PREPROCESSING = Preprocessing(key=None, scale=1.0)
