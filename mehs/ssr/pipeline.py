"""Input RGB → predicted HS cube, with the paper's switches (§3.3).

``predict(model, rgb, preprocess=..., restore=...)``:

1. ``x = reinhard(rgb)`` when ``preprocess`` is on, else ``x = rgb``;
2. ``S = model(x)`` (contract: float32 ``(H, W, B)``, finite);
3. with ``restore`` on: ``HS = (X+Y+Z)_rgb / (X+Y+Z)_S · S`` using the
   *unprocessed* input (:func:`mehs.ssr.luminance.restore_luminance`);
   with ``restore`` off and ``preprocess`` on, the model's output is taken to be
   in the tone-mapped domain and mapped back with the inverse Reinhard
   operator band by band; with both off, ``HS = S``.
4. The model's bands are matched to the requested ``wavelengths`` (the
   dataset's): they must be present in the model's band set (within 0.01 nm).

Self-contained models: a model with a ``preprocessing`` attribute (e.g. the
networks of :mod:`mehs.ssr.net`, ``"reinhard"`` or ``None``) applies its own
input pre-processing, so step 1 is skipped for it whatever ``preprocess`` says;
one with ``restores_luminance = True`` has already done step 3 (doing it again
changes nothing). :func:`mehs.ssr.evaluate.evaluate` scores such models only
under the settings they were built for.
"""

from __future__ import annotations

import numpy as np

from mehs.errors import InputError
from mehs.ssr.luminance import restore_luminance
from mehs.ssr.contract import check_output, check_rgb
from mehs.ssr.preprocess import inverse_reinhard, reinhard


def band_indices(model_wl: np.ndarray, target_wl: np.ndarray, name: str = "model") -> np.ndarray | None:
    """Indices of ``target_wl`` in ``model_wl`` (``None`` if identical); error if any is missing."""
    mw = np.asarray(model_wl, dtype=np.float64)
    tw = np.asarray(target_wl, dtype=np.float64)
    if mw.shape == tw.shape and np.allclose(mw, tw, atol=0.01):
        return None
    idx = np.abs(mw[None, :] - tw[:, None]).argmin(1)
    miss = np.abs(mw[idx] - tw) > 0.01
    if np.any(miss):
        raise InputError(f"{name}: its bands ({mw.size}, {mw[0]:g}..{mw[-1]:g} nm) lack "
                         f"{tw[miss][:5].tolist()} nm of the dataset")
    return idx


def predict(model, rgb: np.ndarray, *, preprocess: bool = False, restore: bool = True,
            wavelengths: np.ndarray | None = None) -> np.ndarray:
    """Run ``model`` on linear ``rgb`` float32 ``(H, W, 3)`` → float32 ``(H, W, B)``.

    ``wavelengths`` (the dataset's bands) selects the model's output bands;
    default: all of them.
    """
    name = getattr(model, "name", "model")
    rgb = check_rgb(rgb, name)
    own_pp = hasattr(model, "preprocessing")
    x = reinhard(rgb) if preprocess and not own_pp else rgb
    model_wl = np.asarray(model.wavelengths, dtype=np.float64)
    S = check_output(np.asarray(model(x)), rgb.shape, model_wl, name)
    if restore:
        out = restore_luminance(S, rgb, model_wl)
    elif preprocess and not own_pp:
        out = inverse_reinhard(S)
    else:
        out = S
    if wavelengths is not None:
        idx = band_indices(model_wl, wavelengths, name)
        if idx is not None:
            out = out[..., idx]
    return np.ascontiguousarray(out, dtype=np.float32)
