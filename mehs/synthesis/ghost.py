"""Ghost (scene motion) detection by a noise-calibrated consistency test.

In a static scene the per-exposure radiance estimates ``y_j/t_j`` of a
pixel agree with the merged ``X`` within their noise. The merge kernel
accumulates, per pixel, ``χ² = Σ_bands Σ_usable (y_j/t_j − X)² / var_j`` with
``dof = Σ_bands (usable − 1)``; pooling the 204 bands makes the test very
sensitive to anything that moved (a cloud, water) while the noise model keeps
bright and dark pixels on the same footing.

The noise model is measured from the bracket itself
(:mod:`mehs.synthesis.noise`), so for a static scene ``χ²/dof ≈ 1`` at every
signal level. A residual mismatch is still divided out — the median of ``χ²``
over the median of ``χ²_dof``, valid when most pixels are static — before the
comparison with the χ² distribution's upper ``α`` quantile at each pixel's
``dof``; but only where it loosens the test (scale ≥ 1). A scale below 1 says
the model overstates the noise, and dividing it out is right only if it does so
by the same factor at every pixel. A read noise set too high does not: it
shrinks the χ² of dark samples and leaves shot-noise-limited ones as they are,
so the median (dark) pixel's scale flagged bright static pixels — a read noise
14× too high flagged 25–30 % of a static frame (2× too high: 3–7 %) at
``α = 1e-4``. An overstated model keeps its own, conservative, test; the fitted
ratio is reported (:attr:`GhostResult.fit`). Isolated detections are dropped
(fewer than ``min_pixels`` connected pixels) and the mask is grown by ``grow``
pixels to cover the soft edges of a moving object.

References
----------
- Granados, M., Kim, K. I., Tompkin, J. and Theobalt, C. (2013). Automatic
  noise modeling for ghost-free HDR reconstruction. ACM TOG 32(6).
- Tursun, O. T., Akyüz, A. O., Erdem, A. and Erdem, E. (2015). The state of the
  art in HDR deghosting: a survey and evaluation. Computer Graphics Forum 34(2).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from mehs.errors import InputError


@dataclass
class GhostResult:
    """Output of :func:`detect_ghosts`.

    Attributes
    ----------
    mask
        bool ``(lines, samples)``: pixels whose exposures disagree.
    score
        float32 ``(lines, samples)``: ``χ²/(scale·dof)`` (≈ 1 for a static pixel; 0 where dof = 0).
    fraction
        Fraction of pixels flagged.
    scale
        The noise-model correction applied (≈ 1 when the noise model fits; ≥ 1 unless
        given): the median over pixels of the per-level scale with ``scale="level"``.
    fit
        Median over pixels of ``χ²`` over its median under the model (NaN where no
        pixel has ``dof > 0``): below 1 the noise model overstates the noise, which
        is reported here but not divided out.
    """

    mask: np.ndarray
    score: np.ndarray
    fraction: float
    scale: float
    alpha: float
    fit: float = float("nan")


#: The smallest χ² scale taken from the data (``scale="auto"`` / ``"level"``): it may
#: loosen the noise model's test, never tighten it (see the module docstring).
MIN_SCALE = 1.0


def _level_scale(ratio: np.ndarray, level: np.ndarray, bins: int = 16,
                 window: int = 5) -> np.ndarray:
    """Per-pixel χ² scale as a smooth function of signal level.

    Median of ``ratio`` (χ² over its median under the model) in ``bins``
    quantile bins of ``level``, smoothed by a running median over ``window``
    bins — so a moving object that fills one or two bins cannot raise its own
    scale — and interpolated in log level. Never below the global median (nor,
    in :func:`detect_ghosts`, below :data:`MIN_SCALE`).
    """
    lv = np.log(np.maximum(level, 1e-30))
    edges = np.quantile(lv, np.linspace(0, 1, bins + 1))
    idx = np.clip(np.searchsorted(edges, lv, side="right") - 1, 0, bins - 1)
    med = np.array([np.median(ratio[idx == b]) if np.any(idx == b) else np.nan
                    for b in range(bins)])
    cen = np.array([np.median(lv[idx == b]) if np.any(idx == b) else np.nan for b in range(bins)])
    ok = np.isfinite(med) & np.isfinite(cen)
    med, cen = med[ok], cen[ok]
    h = window // 2
    sm = np.array([np.median(med[max(0, i - h):i + h + 1]) for i in range(med.size)])
    glob = float(np.median(ratio))
    return np.maximum(np.interp(lv, cen, sm), glob)


def _unique_inverse(v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``np.unique(v, return_inverse=True)`` of non-negative integers, by counting, not sorting
    (the dof of a 512² frame: 25 ms → 2 ms)."""
    if v.dtype.kind not in "iu" or v.size == 0:
        return np.unique(v, return_inverse=True)
    counts = np.bincount(v)
    values = np.flatnonzero(counts)
    lookup = np.zeros(counts.size, dtype=np.intp)
    lookup[values] = np.arange(values.size)
    return values, lookup[v]


def detect_ghosts(chi2: np.ndarray, dof: np.ndarray, *, alpha: float = 1e-4,
                  scale: float | str = "auto", min_pixels: int = 3,
                  grow: int = 1, level: np.ndarray | None = None) -> GhostResult:
    """Flag pixels whose exposures are inconsistent with their noise.

    Parameters
    ----------
    chi2, dof
        ``(lines, samples)`` statistic and degrees of freedom from the merge.
    alpha
        False-alarm probability per static pixel under the (rescaled) model.
    scale
        ``"auto"`` (median of χ² / median of χ²_dof over the frame), ``"level"``
        (that ratio as a smooth function of ``level``, for recovered response
        curves whose error depends on the signal level; ``"auto"`` when fewer than
        64 pixels have ``dof > 0``), or a fixed number (1 trusts the noise model).
        The data-derived scales are never below :data:`MIN_SCALE` (1): an
        overstated noise model is not tightened.
    level
        ``(lines, samples)`` finite signal level (e.g. the mean radiance) for
        ``scale="level"``.
    min_pixels
        Connected groups smaller than this are dropped.
    grow
        Dilate the mask by this many pixels (8-connected).
    """
    chi2 = np.asarray(chi2, dtype=np.float64)
    dof = np.asarray(dof)
    if chi2.shape != dof.shape or chi2.ndim != 2:
        raise InputError(f"chi2 and dof must be matching 2-D arrays, got {chi2.shape}, {dof.shape}")
    if not 0 < alpha < 1:
        raise InputError(f"alpha must be in (0, 1), got {alpha}")
    if np.isnan(chi2).any():
        # one NaN made the frame's median NaN, and the scale fell back to 1 unnoticed
        raise InputError(f"chi2 has {int(np.isnan(chi2).sum())} NaN pixels (a broken "
                         "consistency statistic)")
    if isinstance(scale, str) and scale not in ("auto", "level"):
        raise InputError(f"scale must be 'auto', 'level' or a positive number, got {scale!r}")
    has = dof > 0
    ud = inv = None
    fit = float("nan")
    ratio = None
    if has.any():
        ud, inv = _unique_inverse(dof[has])
        # the median of χ²_ν/ν is below 1 for small ν (0.45 at ν = 1): compare
        # with each pixel's own χ² median, or few-band cubes get a wrong scale
        ratio = chi2[has] / chdtri(ud, 0.5)[inv]
        fit = float(np.median(ratio))
    if scale == "level":
        if level is None or np.shape(level) != chi2.shape:
            raise InputError("scale='level' needs a level array shaped like chi2")
        lev = np.asarray(level, dtype=np.float64)
        if not np.all(np.isfinite(lev[has])):
            raise InputError("scale='level' needs a finite level at every pixel with dof > 0")
        if has.sum() >= 64:
            sl = np.ones(chi2.shape)
            sl[has] = np.maximum(_level_scale(ratio, lev[has]), MIN_SCALE)
            s = float(np.median(sl[has]))
            score = np.zeros(chi2.shape, dtype=np.float32)
            score[has] = chi2[has] / (sl[has] * dof[has])
            mask = np.zeros(chi2.shape, dtype=bool)
            thr = chdtri(ud, alpha)[inv]
            mask[has] = chi2[has] / sl[has] > thr
            return _finish(mask, score, s, alpha, min_pixels, grow, fit)
        scale = "auto"
    if scale == "auto":
        s = fit if np.isfinite(fit) and fit > 0 else 1.0
        # an overstated model is not tightened: see the module docstring
        s = max(s, MIN_SCALE)
    else:
        try:
            s = float(scale)
        except (TypeError, ValueError):
            s = float("nan")
        if not (np.isfinite(s) and s > 0):
            raise InputError(f"scale must be 'auto', 'level' or a positive number, got {scale!r}")
    score = np.zeros(chi2.shape, dtype=np.float32)
    score[has] = chi2[has] / (s * dof[has])
    mask = np.zeros(chi2.shape, dtype=bool)
    if has.any():
        thr = chdtri(ud, alpha)[inv]
        mask[has] = chi2[has] / s > thr
    return _finish(mask, score, s, alpha, min_pixels, grow, fit)


#: Above this many degrees of freedom the closed-form quantile costs more than scipy's import.
_CLOSED_FORM_MAX_DOF = 1024


def chdtri(dof: np.ndarray, p: float) -> np.ndarray:
    """``scipy.special.chdtri(dof, p)``: the χ² quantile with upper-tail probability ``p``.

    Whole ``dof`` (the merge's) take the closed form of :mod:`mehs.synthesis._chi2`:
    importing scipy.special (scipy.stats before that) cost 0.12–0.8 s of every
    ``mehs fuse`` (issue 16). Anything else goes to scipy.
    """
    dof = np.asarray(dof)
    if (dof.dtype.kind in "iu" and dof.size and dof.min() >= 1
            and dof.max() <= _CLOSED_FORM_MAX_DOF):
        from mehs.synthesis._chi2 import chi2_isf_integer

        return chi2_isf_integer(dof, float(p))
    from scipy.special import chdtri as scipy_chdtri

    return scipy_chdtri(dof, p)


def _finish(mask, score, s, alpha, min_pixels, grow, fit=float("nan")) -> GhostResult:
    # OpenCV, not scipy.ndimage: the fusion writes its mask with OpenCV anyway, and
    # importing ndimage cost 0.05–0.2 s of every `mehs fuse` (issue 16). Same
    # definitions: 8-connected groups; a 3×3 dilation with nothing beyond the border.
    import cv2

    if min_pixels > 1 and mask.any():
        n, lab, stats, _ = cv2.connectedComponentsWithStats(mask.astype(np.uint8),
                                                            connectivity=8, ltype=cv2.CV_32S)
        keep = stats[:, cv2.CC_STAT_AREA] >= min_pixels
        keep[0] = False
        mask = keep[lab]
    if grow > 0 and mask.any():
        mask = cv2.dilate(mask.astype(np.uint8), np.ones((3, 3), np.uint8),
                          iterations=int(grow), borderType=cv2.BORDER_CONSTANT,
                          borderValue=0).astype(bool)
    return GhostResult(mask, score, float(mask.mean()), s, float(alpha), float(fit))


def choose_reference(valid_counts: np.ndarray) -> int:
    """Index of the exposure with the most usable samples inside the ghost region."""
    return int(np.argmax(valid_counts))


def deghost_from_reference(radiance: np.ndarray, ghost_mask: np.ndarray, stack, darks,
                           times_ms: np.ndarray, *, linearise, saturation: np.ndarray,
                           floor: float, calibration: np.ndarray,
                           reference: int | str = "auto", chunk_pixels: int = 4096,
                           clip_negative: bool = True,
                           lower_bound: np.ndarray | None = None) -> int:
    """Replace ghost pixels by the estimate of one reference exposure (in place).

    One exposure for the whole region keeps the moving object in one place (no
    double edges); the values are what the reference exposure saw, at its instant.
    Samples below the noise floor keep the reference value (an unbiased, noisy
    estimate).

    A sample saturated in the reference says only that the radiance at its instant
    was at least ``y_sat/t_ref``; a shorter exposure saw another instant, and in a
    ghost region another scene. So the sample keeps that lower bound and its pixel is
    marked in ``lower_bound`` (the caller flags it saturated, mask bit 1), as the
    merge flags a band saturated in every exposure — flagged, not invented. Saturated
    in every exposure up to the reference: the shortest one's lower bound ``y₀/t₀``,
    the merge's own value (the reference's ``y/t_ref`` read a lamp ``t_ref/t₀`` too
    dark), also marked. Falling back to the longest unsaturated shorter exposure wrote
    its instant instead: on the simulator's drifting cloud 94 % of those samples lay
    5σ or more from the reference's radiance (0.04–2.5×), unflagged; even the values
    consistent with the bound (above it) were 20–50 % off.

    Parameters
    ----------
    radiance
        float32 ``(lines, samples, bands)``, modified in place.
    ghost_mask
        bool ``(lines, samples)``.
    stack, darks, times_ms
        The bracket (shortest first), its ``(samples, bands)`` darks and times.
    linearise
        ``f(raw (n, bands), dark (n, bands), j) -> y (n, bands)`` float64, dark-subtracted
        linear DN (the merge's own linearisation).
    saturation
        ``(bands,)`` raw DN saturation levels.
    reference
        Exposure index, or ``"auto"`` (the one with most usable samples in the region,
        hence the fewest lower bounds).
    clip_negative
        Clip negative estimates to 0, as the merge was asked to.
    lower_bound
        Optional bool ``(lines, samples)`` output: set True at the ghost pixels where
        some band holds a lower bound (saturated in the reference).

    Returns
    -------
    int
        The reference exposure used.
    """
    rows, cols = np.nonzero(ghost_mask)
    P = len(stack)
    if not (isinstance(reference, str) and reference == "auto"):
        # checked before the early return: a frame without ghosts recorded any number
        try:
            ok = float(reference) == int(reference)
        except (TypeError, ValueError):
            ok = False
        if not ok or not 0 <= int(reference) < P:
            raise InputError(f"reference exposure must be 'auto' or an index 0..{P - 1}, "
                             f"got {reference!r}")
    if lower_bound is not None and np.shape(lower_bound) != np.shape(ghost_mask):
        raise InputError(f"lower_bound must be shaped like the ghost mask "
                         f"{np.shape(ghost_mask)}, got {np.shape(lower_bound)}")
    if rows.size == 0:
        return int(P // 2) if reference == "auto" else int(reference)
    if reference == "auto":
        counts = np.zeros(P)
        sel = slice(None, None, max(1, rows.size // 2048))  # a subsample is enough to choose
        for j in range(P):
            raw = np.asarray(stack[j][rows[sel], cols[sel]], dtype=np.float64)
            dk = 0.0 if darks[j] is None else darks[j][cols[sel]]
            y = linearise(raw, dk, j)
            counts[j] = np.count_nonzero((raw < saturation) & (y > floor))
        ref = choose_reference(counts)
    else:
        ref = int(reference)
    for k0 in range(0, rows.size, chunk_pixels):
        r, c = rows[k0:k0 + chunk_pixels], cols[k0:k0 + chunk_pixels]
        raw = np.asarray(stack[ref][r, c], dtype=np.float64)
        dk = 0.0 if darks[ref] is None else darks[ref][c]
        est = linearise(raw, dk, ref) / times_ms[ref]
        bound = raw >= saturation       # the reference's own y_sat/t_ref: a lower bound
        if bound.any() and ref > 0:
            # saturated in every shorter exposure too: the shortest one's bound y₀/t₀
            everywhere = bound.copy()
            for j in range(ref - 1, -1, -1):
                rj = np.asarray(stack[j][r, c], dtype=np.float64)
                everywhere &= rj >= saturation
                if not everywhere.any():
                    break
            if everywhere.any():
                d0 = 0.0 if darks[0] is None else darks[0][c]
                x0 = linearise(rj, d0, 0) / times_ms[0]       # j == 0 here
                est[everywhere] = x0[everywhere]
        if lower_bound is not None:
            lower_bound[r, c] |= bound.any(axis=1)
        if clip_negative:
            est = np.maximum(est, 0.0)
        radiance[r, c] = (est * calibration).astype(np.float32)
    return ref
