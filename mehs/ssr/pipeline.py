"""Input RGB → predicted HS cube, with the paper's switches (§3.3).

``predict(model, rgb, preprocessing=..., restore=...)``:

1. ``x = preprocessing(rgb)`` (a :class:`~mehs.ssr.preprocess.Preprocessing`:
   Reinhard at its recorded key/scale) when given, else ``x = rgb``;
   ``preprocess=True`` is the older spelling of the paper's fixed-scale operator;
2. ``S = model(x)`` (contract: float32 ``(H, W, B)``, finite);
3. with ``restore`` on: ``HS = (X+Y+Z)_rgb / (X+Y+Z)_S · S`` using the
   *unprocessed* input (:func:`mehs.ssr.luminance.restore_luminance`); the
   pixels that get its flat-spectrum fallback (``X+Y+Z ≤ 0``) are counted;
   with ``restore`` off and pre-processing on, the model's output is taken to be
   in the tone-mapped domain and mapped back with the inverse Reinhard
   operator band by band (at the same scale); with both off, ``HS = S``.
4. The model's bands are matched to the requested ``wavelengths`` (the
   dataset's): they must be present in the model's band set (within 0.01 nm).

Self-contained models (:func:`mehs.ssr.contract.applies_preprocessing`, e.g. the
networks) apply their own pre-processing, so step 1 is skipped for them. A
model that restores luminance inside ``__call__`` and offers
``standard_spectrum(rgb)`` is run through that instead, so step 3 (and its
fallback count) happens here; one that offers nothing reports the count as
``None`` (unknown).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from mehs.errors import InputError
from mehs.ssr.contract import applies_preprocessing, check_output, check_rgb, trained_for
from mehs.ssr.luminance import restore_luminance
from mehs.ssr.preprocess import PAPER_PREPROCESSING, Preprocessing, inverse_reinhard


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
            wavelengths: np.ndarray | None = None,
            preprocessing: Preprocessing | None = None, return_stats: bool = False):
    """Run ``model`` on linear ``rgb`` float32 ``(H, W, 3)`` → float32 ``(H, W, B)``.

    ``preprocessing`` (or ``preprocess=True`` for the paper's fixed-scale
    operator) is applied unless the model applies its own. ``wavelengths``
    (the dataset's bands) selects the model's output bands; default: all.
    With ``return_stats`` returns ``(cube, stats)``: ``stats["restore_fallback"]`` the
    number of pixels whose restoration fell back to a flat spectrum (``None`` without
    restoration), ``stats["restore_fallback_mask"]`` those pixels, ``(H, W)`` bool or ``None``.
    """
    name = getattr(model, "name", "model")
    rgb = check_rgb(rgb, name)
    spec = preprocessing if preprocessing is not None else (PAPER_PREPROCESSING if preprocess else None)
    own_pp = applies_preprocessing(model)
    x = spec(rgb) if spec is not None and not own_pp else rgb
    model_wl = np.asarray(model.wavelengths, dtype=np.float64)
    stats: dict[str, Any] = {"restore_fallback": None, "restore_fallback_mask": None}
    inner = getattr(model, "standard_spectrum", None)
    restores_inside = trained_for(model).output == "shape" and own_pp
    if restore and restores_inside and callable(inner):
        S = check_output(np.asarray(inner(x)), rgb.shape, model_wl, name)
    else:
        S = check_output(np.asarray(model(x)), rgb.shape, model_wl, name)
    if restore and not (restores_inside and not callable(inner)):
        out, fell = restore_luminance(S, rgb, model_wl, return_fallback="mask")
        stats["restore_fallback"] = int(np.count_nonzero(fell))
        stats["restore_fallback_mask"] = fell
    elif restore:
        out = restore_luminance(S, rgb, model_wl)  # a no-op on an already restored output
    elif spec is not None and not own_pp:
        out = inverse_reinhard(S) / np.float32(spec.factor(rgb))
    else:
        out = S
    if wavelengths is not None:
        idx = band_indices(model_wl, wavelengths, name)
        if idx is not None:
            out = out[..., idx]
    out = np.ascontiguousarray(out, dtype=np.float32)
    return (out, stats) if return_stats else out
