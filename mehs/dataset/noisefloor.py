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
default (``poisson``) estimator's variance at the levels where the test decides (no
exposure saturates there); the other estimators weight the exposures otherwise
(inverse variance: lower variance, Robertson about the same) and elements saturated in
the longest exposures are noisier than the formula says — both only ever keep a pixel the
exact figure would drop, never the reverse. A per-column (flat-field) calibration
enters with its median over columns.

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


def native_variance_terms(noise: dict[str, Any], times_ms) -> tuple[float, float, float]:
    """``(A/T², gain/T, rel²·S/T²)`` of the Poisson-pooled native estimate (DN/ms units).

    ``noise``: the fusion summary's ``noise`` record (``gain_dn_per_e``, ``read_noise_dn``,
    ``dark_current_dn_per_ms``, ``relative``).
    """
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
    T = float(t.sum())
    A = float(np.sum(read * read + gain * dc * t))
    S = float(np.sum(t * t))
    return A / (T * T), gain / T, rel * rel * S / (T * T)


def band_noise_model(noise: dict[str, Any], times_ms, matrix: np.ndarray,
                     factor: np.ndarray | float = 1.0) -> dict[str, Any]:
    """The per-band noise model of the 31-band cube (before the radiance scale).

    ``matrix`` ``(31, n_src)``: the resampling matrix (rows sum to 1); ``factor``
    (scalar or ``(n_src,)``): cube units per DN/ms of each native band. Returns the
    record ``{"format", "zero", "shot", "rel", "source"}`` (lists of 31 floats).
    """
    m = np.asarray(matrix, dtype=np.float64)
    f = np.broadcast_to(np.asarray(factor, dtype=np.float64), (m.shape[1],))
    a, g, r = native_variance_terms(noise, times_ms)
    m2 = m * m
    zero = a * (m2 @ (f * f))
    shot = g * (m2 @ f)
    rel = r * m2.sum(1)          # f cancels: (rel·f·X)² = (rel·y)²
    return {"format": NOISE_MODEL_FORMAT, "zero": zero.tolist(), "shot": shot.tolist(),
            "rel": rel.tolist(), "source": str(noise.get("source", "fusion noise model"))}


def scaled(model: dict[str, Any], scale: float) -> dict[str, Any]:
    """The model of the cube multiplied by ``scale`` (the half-float radiance scale)."""
    s = float(scale)
    out = dict(model)
    out["zero"] = (np.asarray(model["zero"]) * s * s).tolist()
    out["shot"] = (np.asarray(model["shot"]) * s).tolist()
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


def sigma(y: np.ndarray, model: dict[str, Any]) -> np.ndarray:
    """float32 noise σ of each element of ``y (..., B)`` under the recorded ``model``."""
    y = np.asarray(y, dtype=np.float32)
    zero, shot, rel = _terms(model, y.shape[-1])
    yp = np.maximum(y, np.float32(0))
    return np.sqrt(zero + shot * yp + rel * yp * yp)


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
    noise model and exposure times; ``None`` when the summary has none."""
    from mehs.bandmeta import bad_bands
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
    return band_noise_model(noise, times, m, calibration_factor(cal, cube.bands))


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
