"""Input pre-processing for SSR models (paper §3.3): Reinhard's global operator.

``f(x) = x / (1 + x)`` maps HDR linear RGB ``[0, ∞)`` into ``[0, 1)`` so that a
model trained on display-range data sees inputs of the range it knows. It is
applied per channel, as in the paper.

References
----------
- Reinhard, E., Stark, M., Shirley, P., Ferwerda, J. (2002). Photographic tone
  reproduction for digital images. ACM Transactions on Graphics 21(3), 267–276.
"""

from __future__ import annotations

import numpy as np

#: Largest value :func:`inverse_reinhard` accepts before clipping (its pole is at 1).
INVERSE_CLIP = 1.0 - 1e-6


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


#: Dispatcher: pre-processing name → (forward, inverse).
PREPROCESS_METHODS = {
    "reinhard": (reinhard, inverse_reinhard),
}
