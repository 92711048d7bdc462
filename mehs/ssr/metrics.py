"""Per-image error metrics for SSR, as in NTIRE/MST++ and the paper (§3.6.3).

All functions take a prediction and a ground truth of shape ``(H, W, B)`` (or
``(N, B)``), an optional boolean ``valid`` mask ``(H, W)`` (True = use the pixel;
build it from the dataset mask with ``mask == 0``) and an optional border
``crop`` (pixels removed on every side before anything else).

Definitions (documented choices)
--------------------------------
SAM
    Mean over pixels of ``arccos(ŷ·y / (‖ŷ‖‖y‖))`` in **degrees**, the cosine
    clipped to ``[−1, 1]``. Pixels where either spectrum has zero norm have no
    angle: they are excluded from the mean and counted (``sam_excluded``).
MRAE
    NTIRE form ``mean(|ŷ − y| / y)`` over all valid (pixel, band) elements.
    Elements with ``y ≤ 0`` have no relative error: they are **excluded** and
    counted (``mrae_excluded``); no ε is added, so on strictly positive data the
    value equals MST++'s ``Loss_MRAE`` exactly.
RMSE
    ``sqrt(mean((ŷ − y)²))`` over valid elements, in the data's units.
PSNR
    ``10·log10(peak² / MSE)`` with **peak = the maximum of the ground truth over
    the valid pixels of that image** by default (HDR data has no fixed range);
    pass ``peak=1`` for the NTIRE/MST++ peak on [0, 1] data (MST++'s ``Loss_PSNR`` also
    clamps both images to [0, 1] first; mehs scores the prediction as given, so a
    prediction outside [0, 1] scores lower here than there). The MSE is
    floored at ``peak²·10⁻¹²`` so identical images give 120 dB, not inf.

A metric with no usable element returns ``None`` (never NaN); the summaries
skip it and report how many images were skipped.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from mehs.errors import InputError
from mehs.ssr.contract import all_finite

#: PSNR ceiling (dB) reached when the MSE is 0.
PSNR_MAX_DB = 120.0

METRIC_NAMES = ("sam", "mrae", "rmse", "psnr")
#: Whether a larger value is better, per metric.
HIGHER_IS_BETTER = {"sam": False, "mrae": False, "rmse": False, "psnr": True}


def _prepare(pred: np.ndarray, gt: np.ndarray, valid: np.ndarray | None,
             crop: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Crop, check and flatten to ``(N, B)`` float64 arrays of the valid pixels."""
    pred = np.asarray(pred)
    gt = np.asarray(gt)
    if pred.shape != gt.shape:
        raise InputError(f"prediction shape {pred.shape} differs from ground truth {gt.shape}")
    if gt.ndim not in (2, 3):
        raise InputError(f"expected (H, W, B) or (N, B) arrays, got shape {gt.shape}")
    if valid is not None:
        valid = np.asarray(valid, dtype=bool)
        if valid.shape != gt.shape[:-1]:
            raise InputError(f"mask shape {valid.shape} does not match image {gt.shape[:-1]}")
    crop = int(crop)
    if crop < 0:
        raise InputError(f"crop must be ≥ 0, got {crop}")
    if crop:
        if gt.ndim != 3 or min(gt.shape[:2]) <= 2 * crop:
            raise InputError(f"crop {crop} leaves nothing of an image of shape {gt.shape}")
        sl = (slice(crop, -crop), slice(crop, -crop))
        pred, gt = pred[sl], gt[sl]
        valid = None if valid is None else valid[sl]
    b = gt.shape[-1]
    pred = pred.reshape(-1, b)
    gt = gt.reshape(-1, b)
    if valid is not None:
        v = valid.reshape(-1)
        pred, gt = pred[v], gt[v]
    pred = pred.astype(np.float64, copy=False)
    gt = gt.astype(np.float64, copy=False)
    if not (all_finite(pred) and all_finite(gt)):
        raise InputError("prediction or ground truth contains NaN or inf")
    return pred, gt, valid


def sam_map(pred: np.ndarray, gt: np.ndarray) -> np.ndarray:
    """Per-pixel spectral angle in degrees, shape ``pred.shape[:-1]``, float32.

    Pixels where either spectrum has zero norm are NaN **in this map only**
    (it feeds figures); the scalar metrics never return NaN.
    """
    pred = np.asarray(pred, dtype=np.float64)
    gt = np.asarray(gt, dtype=np.float64)
    dot = np.einsum("...b,...b->...", pred, gt)
    norm = np.sqrt(np.einsum("...b,...b->...", pred, pred) *
                   np.einsum("...b,...b->...", gt, gt))
    with np.errstate(invalid="ignore", divide="ignore"):
        cos = np.clip(dot / norm, -1.0, 1.0)
    ang = np.degrees(np.arccos(cos))
    ang[norm == 0] = np.nan
    return ang.astype(np.float32)


def sam_deg(pred, gt, *, valid=None, crop: int = 0, return_count: bool = False):
    """Mean spectral angle in degrees (see module notes); ``None`` if no pixel qualifies.

    With ``return_count=True`` returns ``(sam, n_excluded_zero_norm)``.
    """
    p, g, _ = _prepare(pred, gt, valid, crop)
    dot = np.einsum("nb,nb->n", p, g)
    norm = np.sqrt(np.einsum("nb,nb->n", p, p) * np.einsum("nb,nb->n", g, g))
    ok = norm > 0
    n_excl = int(np.count_nonzero(~ok))
    val = (float(np.degrees(np.arccos(np.clip(dot[ok] / norm[ok], -1, 1))).mean())
           if ok.any() else None)
    return (val, n_excl) if return_count else val


def mrae(pred, gt, *, valid=None, crop: int = 0, return_count: bool = False):
    """NTIRE mean relative absolute error; elements with ``y ≤ 0`` excluded and counted."""
    p, g, _ = _prepare(pred, gt, valid, crop)
    ok = g > 0
    n_excl = int(np.count_nonzero(~ok))
    val = float((np.abs(p[ok] - g[ok]) / g[ok]).mean()) if ok.any() else None
    return (val, n_excl) if return_count else val


def rmse(pred, gt, *, valid=None, crop: int = 0):
    """Root mean square error over valid elements; ``None`` if there are none."""
    p, g, _ = _prepare(pred, gt, valid, crop)
    if p.size == 0:
        return None
    return float(np.sqrt(np.mean((p - g) ** 2)))


def psnr(pred, gt, *, valid=None, crop: int = 0, peak: float | None = None):
    """PSNR in dB; ``peak`` defaults to the ground truth's maximum over valid pixels."""
    p, g, _ = _prepare(pred, gt, valid, crop)
    if p.size == 0:
        return None
    pk = float(g.max()) if peak is None else float(peak)
    if not pk > 0:
        return None
    mse = max(float(np.mean((p - g) ** 2)), pk * pk * 10 ** (-PSNR_MAX_DB / 10))
    return float(10 * np.log10(pk * pk / mse))


def _floor_rows(floor, gt, valid, crop: int) -> np.ndarray | None:
    """``floor`` as rows matching :func:`_prepare`'s ``(N, B)`` (or ``(B,)``); checked."""
    if floor is None:
        return None
    f = np.asarray(floor, dtype=np.float64)
    gshape = np.shape(gt)
    if f.shape == (gshape[-1],):
        out = f
    elif f.shape == tuple(gshape):
        out = _prepare(f, f, valid, crop)[0]
    else:
        raise InputError(f"MRAE floor has shape {f.shape}, expected ({gshape[-1]},) or {gshape}")
    if np.isnan(out).any():
        raise InputError("MRAE floor contains NaN")
    return out


def image_metrics(pred: np.ndarray, gt: np.ndarray, *, valid: np.ndarray | None = None,
                  crop: int = 0, peak: float | None = None, mrae_threshold: float = 0.0,
                  mrae_relative: bool = False,
                  mrae_band_mask: np.ndarray | None = None,
                  mrae_floor: np.ndarray | None = None) -> dict[str, Any]:
    """All four metrics of one image plus the counts behind them.

    Returns
    -------
    dict
        ``sam, mrae, rmse, psnr`` (float or ``None``), ``n_pixels`` (valid pixels
        scored), ``sam_excluded`` (zero-norm pixels), ``mrae_excluded``
        (elements with y ≤ 0), ``peak`` (the PSNR peak used), and
        ``band_mrae`` (list of B per-band MRAE values, ``None`` where undefined).

    MRAE element rule: elements with ``y > mrae_threshold`` (× the ground
    truth's maximum over the scored pixels when ``mrae_relative``) count; the
    others are excluded and counted. ``mrae_band_mask`` (bool ``(B,)``)
    restricts the scalar MRAE to those bands (``band_mrae`` keeps every band).
    ``mrae_floor`` (float ``(B,)`` or the ground truth's shape ``(H, W, B)`` / ``(N, B)``):
    an element also needs ``y > floor`` — e.g. 10·σ of the ground truth's own noise
    (:func:`mehs.dataset.noisefloor.mrae_floor`), where ``|ŷ − y| / y`` measures the
    noise of ``y`` rather than the model; excluded elements are counted in
    ``mrae_excluded`` and ``mrae_floor_excluded`` (those only the floor excluded).
    The default (0, absolute, all bands, no floor) is the NTIRE form of the module notes.
    """
    fl = _floor_rows(mrae_floor, gt, valid, crop)
    p, g, _ = _prepare(pred, gt, valid, crop)
    out: dict[str, Any] = {"n_pixels": int(p.shape[0])}
    dot = np.einsum("nb,nb->n", p, g)
    norm = np.sqrt(np.einsum("nb,nb->n", p, p) * np.einsum("nb,nb->n", g, g))
    ok = norm > 0
    out["sam"] = (float(np.degrees(np.arccos(np.clip(dot[ok] / norm[ok], -1, 1))).mean())
                  if ok.any() else None)
    out["sam_excluded"] = int(np.count_nonzero(~ok))
    thr = float(mrae_threshold) * (float(g.max()) if mrae_relative and g.size else 1.0)
    pos = g > max(thr, 0.0)
    if fl is not None:
        above = g > fl
        out["mrae_floor_excluded"] = int(np.count_nonzero(pos & ~above))
        pos &= above
    with np.errstate(invalid="ignore", divide="ignore"):
        rel = np.where(pos, np.abs(p - g) / np.where(pos, g, 1.0), 0.0)
    n_pos = pos.sum(0)
    sel = np.ones(g.shape[-1], bool) if mrae_band_mask is None else np.asarray(mrae_band_mask, bool)
    if sel.shape != (g.shape[-1],):
        raise InputError(f"MRAE band mask has shape {sel.shape}, expected ({g.shape[-1]},)")
    out["mrae_excluded"] = int(np.count_nonzero(~pos[:, sel]))
    n_sel = n_pos[sel].sum()
    out["mrae"] = float(rel[:, sel].sum() / n_sel) if n_sel else None
    band = rel.sum(0) / np.maximum(n_pos, 1)
    out["band_mrae"] = [float(v) if n else None for v, n in zip(band, n_pos)]
    if p.size:
        mse = float(np.mean((p - g) ** 2))
        out["rmse"] = float(np.sqrt(mse))
        pk = float(g.max()) if peak is None else float(peak)
        out["peak"] = pk
        out["psnr"] = (float(10 * np.log10(pk * pk / max(mse, pk * pk * 10 ** (-PSNR_MAX_DB / 10))))
                       if pk > 0 else None)
    else:
        out.update(rmse=None, psnr=None, peak=None)
    return out
