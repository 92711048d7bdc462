"""Ground truth not resolved above its own noise: the noise of a dataset's 31-band cube.

A fused cube keeps its signed, unbiased estimates, so a pixel of (almost) no light holds
noise around zero. Scored as ground truth, such values dominate a scene's MRAE
(``|ŷ − y| / y`` for ``y`` a small positive noise sample is huge) and its SAM (the angle
of a noise vector is the noise's). Against the simulator's truth (48² ColorChecker at
10⁻² of its light, Smits): MRAE 1.21 against the dataset's ``hs.hdr``, 0.30 against the
noise-free radiance; the pixels below a spectrum SNR of 10 held 92 % of the MRAE sum.

The noise model of the stored cube
----------------------------------
The merge's noise model (measured from the bracket by photon transfer, recorded in
``fusion.json``: ``var(y_j) = gain·y_j + a_j + (rel·y_j)²``, ``a_j = read² + gain·D·t_j``)
gives the variance of the Poisson-pooled estimate ``X = Σ y_j / Σ t_j`` (DN/ms) of a
native band when every exposure is usable::

    var(X) = gain·X / T + A / T² + rel²·X²·S / T²,   T = Σ t_j,  A = Σ a_j,  S = Σ t_j²

A calibration factor ``f`` (cube units per DN/ms) and the resampling to 31 bands
(``y_b = Σ_k M_bk X_k``, independent native bands, ``X_k ≈ y_b`` across a band's window)
turn it into a per-band model of the stored values ``y`` (the radiance scale ``s``
included)::

    σ_b²(y) = zero_b + shot_b·max(y, 0) + rel_b·y²

``zero_b = s²·A/T²·Σ_k M_bk² f_k²``, ``shot_b = s·gain/T·Σ_k M_bk² f_k``,
``rel_b = rel²·S/T²·Σ_k M_bk²``. This is the
default (``poisson``) estimator's variance where every exposure is usable. Where the
longest exposures saturate, the merge pools only the shorter ones (variance up to
``T/t₀`` times larger): the fusion records each exposure's saturation level
(``fusion.json`` ``saturation_linear_dn``) and the model steps to the shorter exposures'
terms at the levels where the merge drops them (``"exposures"``,
:mod:`mehs.dataset.noisefloor_sat`). Against the simulator (window scene, ×4…×150),
``|hs − truth|/σ`` had std 1.9, 3.4, 6.8 and 15 with 1, 2, 3 and 4 exposures saturated;
with the steps 1.0–1.05 (1.03–1.08 under the sodium lamp). A step is at the band's
M-weighted native limit (a spectrum flat across the band's window): elements within a few
per cent of it, or whose window straddles it, are between the two figures. The other
estimators weight the exposures otherwise (against the simulator: inverse variance std
0.99, Robertson 1.12, Debevec 1.09 of this model's σ). A per-column (flat-field)
calibration enters with its median over columns.

The test
--------
A pixel is *not resolved above the noise* (mask bit :data:`MASK_UNRESOLVED`) when the
SNR of its 31-band spectrum ``‖y‖ / ‖σ(y)‖`` is below :data:`RESOLVED_SNR` = 10: Currie's
limit of quantification (a relative standard uncertainty of 10 %; Currie 1968, IUPAC
1995), the level from which a measured value is a quantity rather than a detection. At
that SNR the spectrum's own angular noise is ≈ 1/10 rad (5.7°), the size of the SAM
values being compared (the paper's ME HS table: 5.5–6.5°). The threshold is a multiple
of each pixel's own noise, which the bracket measured — no radiance level enters.
Element by element, the same model gives MRAE's floor ``y_b ≤ 10·σ_b(y)``
(:func:`mrae_floor`), which a scored element must exceed as it must exceed 0.

References
----------
- Currie, L. A. (1968). Limits for qualitative detection and quantitative determination.
  Analytical Chemistry 40(3), 586–593.
- IUPAC (1995). Nomenclature in evaluation of analytical methods including detection and
  quantification capabilities. Pure Appl. Chem. 67(10), 1699–1723.
- Hanji, P. et al. (2020). Noise-aware merging of high dynamic range image stacks
  without camera calibration. ECCV Workshops (the Poisson estimator).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from mehs.errors import InputError

#: Mask bit of a pixel whose ground truth is not resolved above its noise.
MASK_UNRESOLVED = 8
#: Spectrum SNR below which a pixel is not resolved (Currie's limit of quantification).
RESOLVED_SNR = 10.0
#: The record's format (``quality.noise_model``).
NOISE_MODEL_FORMAT = "mehs-band-noise/1"


def _noise_values(noise: dict[str, Any], times_ms) -> tuple[np.ndarray, float, float, float, float]:
    """``(t, gain, read, dc, rel)`` of a fusion summary's ``noise`` record, checked."""
    t = np.asarray(times_ms, dtype=np.float64).reshape(-1)
    try:
        gain = float(noise["gain_dn_per_e"])
        read = float(noise["read_noise_dn"])
        dc = float(noise.get("dark_current_dn_per_ms") or 0.0)
        rel = float(noise.get("relative") or 0.0)
    except (KeyError, TypeError, ValueError) as exc:
        raise InputError(f"the fusion summary's noise model is incomplete ({exc})") from None
    vals = np.array([gain, read, dc, rel])
    if not (t.size and np.all(np.isfinite(t) & (t > 0)) and np.all(np.isfinite(vals) & (vals >= 0))):
        raise InputError(f"noise model {noise} or exposure times {t.tolist()} are not usable")
    return t, gain, read, dc, rel


def prefix_variance_terms(noise: dict[str, Any], times_ms) -> np.ndarray:
    """float64 ``(P, 3)``: row ``m − 1`` holds ``(A/T², gain/T, rel²·S/T²)`` of the
    Poisson-pooled estimate from the ``m`` shortest exposures (DN/ms units) — the merge's
    estimate where the longer ``P − m`` saturate. ``times_ms`` ascending (as recorded)."""
    t, gain, read, dc, rel = _noise_values(noise, times_ms)
    t = np.sort(t)
    T = np.cumsum(t)
    A = np.cumsum(read * read + gain * dc * t)
    S = np.cumsum(t * t)
    return np.stack([A / (T * T), gain / T, rel * rel * S / (T * T)], axis=1)


def native_variance_terms(noise: dict[str, Any], times_ms) -> tuple[float, float, float]:
    """``(A/T², gain/T, rel²·S/T²)`` of the Poisson-pooled native estimate (DN/ms units),
    every exposure usable.

    ``noise``: the fusion summary's ``noise`` record (``gain_dn_per_e``, ``read_noise_dn``,
    ``dark_current_dn_per_ms``, ``relative``).
    """
    a, g, r = prefix_variance_terms(noise, times_ms)[-1]
    return float(a), float(g), float(r)


def band_noise_model(noise: dict[str, Any], times_ms, matrix: np.ndarray,
                     factor: np.ndarray | float = 1.0,
                     saturation: np.ndarray | None = None) -> dict[str, Any]:
    """The per-band noise model of the 31-band cube (before the radiance scale).

    ``matrix`` ``(31, n_src)``: the resampling matrix (rows sum to 1); ``factor``
    (scalar or ``(n_src,)``): cube units per DN/ms of each native band. Returns the
    record ``{"format", "zero", "shot", "rel", "source"}`` (lists of 31 floats).
    ``saturation`` ``(P, n_src)``: each exposure's linearised saturation level less dark
    (``fusion.json`` ``saturation_linear_dn``); with it the record also holds
    ``"exposures"``, where the merge drops the longest exposures
    (:func:`_exposure_steps`).
    """
    m = np.asarray(matrix, dtype=np.float64)
    f = np.broadcast_to(np.asarray(factor, dtype=np.float64), (m.shape[1],))
    a, g, r = native_variance_terms(noise, times_ms)
    m2 = m * m
    zero = a * (m2 @ (f * f))
    shot = g * (m2 @ f)
    rel = r * m2.sum(1)          # f cancels: (rel·f·X)² = (rel·y)²
    out = {"format": NOISE_MODEL_FORMAT, "zero": zero.tolist(), "shot": shot.tolist(),
           "rel": rel.tolist(), "source": str(noise.get("source", "fusion noise model"))}
    if saturation is not None and len(np.atleast_1d(times_ms)) > 1:
        out["exposures"] = _exposure_steps(noise, times_ms, m, f, saturation)
    return out


def _exposure_steps(noise, times_ms, m: np.ndarray, f: np.ndarray,
                    saturation: np.ndarray) -> dict[str, Any]:
    """The record's ``"exposures"``: ``levels`` ``(31, P−1)`` ascending, the value of a
    band above which the merge has dropped 1, 2, … of the longest exposures (the
    band's native limits weighted as the band averages them: a spectrum flat across
    the band's window), and ``zero``/``shot``/``rel`` ``(P−1,)``, the factors of the
    three terms with that many dropped (the Poisson estimate of the shorter ones)."""
    from mehs.dataset.noisefloor_sat import usable_limits

    ys = np.asarray(saturation, dtype=np.float64)
    if ys.shape != (len(np.atleast_1d(times_ms)), m.shape[1]):
        raise InputError(f"saturation levels of shape {ys.shape} for "
                         f"{len(np.atleast_1d(times_ms))} exposures of {m.shape[1]} bands")
    lim = usable_limits(noise, times_ms, ys)            # (P, n_src) DN/ms
    levels = (m * f) @ lim[1:].T                        # (31, P−1): exposure 1 … P−1
    terms = prefix_variance_terms(noise, times_ms)      # (P, 3): m = 1 … P usable
    full = terms[-1]
    drop = terms[-2::-1]                                # 1, 2, … P−1 dropped
    ratio = np.divide(drop, full, out=np.zeros_like(drop), where=full > 0)
    return {"levels": levels[:, ::-1].tolist(), "zero": ratio[:, 0].tolist(),
            "shot": ratio[:, 1].tolist(), "rel": ratio[:, 2].tolist()}


def scaled(model: dict[str, Any], scale: float) -> dict[str, Any]:
    """The model of the cube multiplied by ``scale`` (the half-float radiance scale)."""
    s = float(scale)
    out = dict(model)
    out["zero"] = (np.asarray(model["zero"]) * s * s).tolist()
    out["shot"] = (np.asarray(model["shot"]) * s).tolist()
    if model.get("exposures") is not None:
        ex = dict(model["exposures"])
        ex["levels"] = (np.asarray(ex["levels"], dtype=np.float64) * s).tolist()
        out["exposures"] = ex
    return out


def _terms(model: dict[str, Any], bands: int) -> tuple[np.ndarray, ...]:
    """``zero, shot, rel`` float32 ``(bands,)`` of a recorded model, checked."""
    if not isinstance(model, dict) or model.get("format") != NOISE_MODEL_FORMAT:
        raise InputError(f"not a band noise model ({NOISE_MODEL_FORMAT}): {model!r:.80}")
    out = []
    for k in ("zero", "shot", "rel"):
        v = np.asarray(model.get(k), dtype=np.float64).reshape(-1)
        if v.shape != (bands,) or not np.all(np.isfinite(v) & (v >= 0)):
            raise InputError(f"band noise model {k!r} must be {bands} finite values ≥ 0")
        out.append(v.astype(np.float32))
    return tuple(out)


def _steps(model: dict[str, Any], bands: int) -> tuple[np.ndarray, np.ndarray] | None:
    """``levels`` float32 ``(bands, K)`` and the factors float32 ``(K + 1, 3)`` (row 0:
    every exposure usable) of a model's ``"exposures"``, checked; ``None`` without."""
    ex = model.get("exposures")
    if ex is None:
        return None
    try:
        lev = np.asarray(ex["levels"], dtype=np.float64)
        fac = np.asarray([ex["zero"], ex["shot"], ex["rel"]], dtype=np.float64).T
    except (KeyError, TypeError, ValueError):
        raise InputError("band noise model 'exposures' needs 'levels', 'zero', 'shot' and "
                         "'rel' (numbers)") from None
    if (lev.ndim != 2 or lev.shape[0] != bands or fac.shape != (lev.shape[1], 3)
            or not (np.all(np.isfinite(lev) & (lev >= 0)) and np.all(np.isfinite(fac) & (fac >= 0)))
            or np.any(np.diff(lev, axis=1) < 0)):
        raise InputError(f"band noise model 'exposures' must hold {bands} rows of ascending "
                         f"levels ≥ 0 and one finite factor ≥ 0 per level for each term")
    return lev.astype(np.float32), np.vstack([np.ones((1, 3)), fac]).astype(np.float32)


def sigma(y: np.ndarray, model: dict[str, Any]) -> np.ndarray:
    """float32 noise σ of each element of ``y (..., B)`` under the recorded ``model``
    (with ``"exposures"``: the terms of the exposures the merge used at that level)."""
    y = np.asarray(y, dtype=np.float32)
    zero, shot, rel = _terms(model, y.shape[-1])
    steps = _steps(model, y.shape[-1])
    yp = np.maximum(y, np.float32(0))
    if steps is None:
        return np.sqrt(zero + shot * yp + rel * yp * yp)
    lev, fac = steps
    n = np.zeros(y.shape, dtype=np.uint8)         # exposures dropped at this level
    for k in range(lev.shape[1]):
        n += yp >= lev[:, k]
    return np.sqrt(zero * fac[:, 0][n] + shot * fac[:, 1][n] * yp
                   + rel * fac[:, 2][n] * yp * yp)


def unresolved(y: np.ndarray, model: dict[str, Any], snr: float = RESOLVED_SNR, *,
               block: int = 256) -> np.ndarray:
    """bool ``(H, W)``: pixels of ``y (H, W, B)`` whose spectrum SNR ``‖y‖/‖σ(y)‖ < snr``.

    ``‖y‖`` of the signed values (``E‖y‖² = ‖μ‖² + ‖σ‖²``: 0.5 % high at the threshold).
    ``block`` lines at a time (the σ cube is never whole in memory).
    """
    if not (np.isfinite(snr) and snr > 0):
        raise InputError(f"the resolved-SNR threshold must be > 0, got {snr}")
    h = y.shape[0]
    out = np.empty(y.shape[:2], dtype=bool)
    k2 = np.float64(snr) ** 2
    for r0 in range(0, h, block):
        yy = np.asarray(y[r0:r0 + block], dtype=np.float32)
        s = sigma(yy, model)
        sig2 = np.einsum("...b,...b->...", s, s, dtype=np.float64)
        y2 = np.einsum("...b,...b->...", yy, yy, dtype=np.float64)
        out[r0:r0 + block] = y2 < k2 * sig2
    return out


def mrae_floor(y: np.ndarray, model: dict[str, Any] | None,
               snr: float = RESOLVED_SNR) -> np.ndarray | None:
    """float32 ``snr·σ(y)`` per element of ``y (..., B)``: MRAE scores an element only
    above it (as the NTIRE rule scores it only above 0); ``None`` without a model."""
    if model is None:
        return None
    return np.float32(snr) * sigma(y, model)


def calibration_factor(calibration, n_src: int) -> np.ndarray | float:
    """Cube units per DN/ms of each source band of a calibrated cube (1 without one).

    A :class:`~mehs.calibration.Calibration` divides by its responsivity per column and
    band; the model takes the median over columns. Only the calibrated bands remain in
    the cube, so the factor has one value per calibrated band.
    """
    if calibration is None:
        return 1.0
    r = np.asarray(calibration.responsivity, dtype=np.float64)
    f = np.median(1.0 / r, axis=0)
    if f.size != n_src:
        raise InputError(f"calibration has {f.size} bands, the fused cube {n_src}")
    return f


def model_for_fused(cube, summary: dict[str, Any], *, method: str, fwhm: float,
                    calibration: str | None = None) -> dict[str, Any] | None:
    """The band noise model of the 31-band cube :func:`~mehs.dataset.cube_figures.to_31_bands`
    makes from the fused ``cube`` (before the radiance scale), from the fusion ``summary``'s
    noise model, exposure times and (when recorded: ``saturation_linear_dn``) saturation
    levels; ``None`` when the summary has no noise model."""
    from mehs.bandmeta import bad_bands
    from mehs.dataset.noisefloor_sat import saturation_levels
    from mehs.rgb import WAVELENGTHS_31
    from mehs.synthesis.resample import resampling_matrix

    noise, times = summary.get("noise"), summary.get("times_ms")
    if not noise or not times:
        return None
    if cube.bands == 31 and np.allclose(cube.wavelengths, WAVELENGTHS_31, atol=1e-6):
        m = np.eye(31)                                   # to_31_bands leaves it as it is
    else:
        m = resampling_matrix(cube.wavelengths, WAVELENGTHS_31, method=method,
                              src_fwhm=cube.fwhm, dst_fwhm=fwhm,
                              exclude=bad_bands(cube.metadata or {}, cube.bands))
    cal = None
    if calibration:
        from mehs.calibration import Calibration

        cal = Calibration.load(calibration)
    ys = saturation_levels(summary, len(times), None if cal is None else cal.bands)
    if ys is not None and ys.shape[1] != cube.bands:
        raise InputError(f"fusion.json saturation levels have {ys.shape[1]} bands, the fused "
                         f"cube {cube.bands}")
    return band_noise_model(noise, times, m, calibration_factor(cal, cube.bands), ys)


def screen(data: np.ndarray, mask: np.ndarray, model: dict[str, Any] | None,
           snr: float = RESOLVED_SNR) -> dict[str, Any]:
    """Set :data:`MASK_UNRESOLVED` in ``mask (H, W)`` (in place) where the stored 31-band
    ``data`` is not resolved; returns the quality figures ``noise_floor_fraction``
    (of all pixels), ``noise_floor_snr`` and ``noise_model`` (``None`` without a model:
    a cube with no bracket, whose noise is unknown — not zero)."""
    if model is None:
        return {"noise_floor_fraction": None, "noise_floor_snr": None, "noise_model": None}
    bad = unresolved(data, model, snr)
    mask[bad] |= np.uint8(MASK_UNRESOLVED)
    return {"noise_floor_fraction": float(np.count_nonzero(bad) / max(1, bad.size)),
            "noise_floor_snr": float(snr), "noise_model": model}
