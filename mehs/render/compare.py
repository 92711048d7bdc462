"""Score renders against the ground-truth-HS render: difference images and numbers.

All images are linear sRGB ``(H, W, 3)`` float32 (spectral renders go through
:func:`mehs.rgb.hdr_rgb` first).

- **Difference image** (paper Figs. 13–14): ``|render − reference| × 5`` per channel,
  exposed with the reference's exposure and sRGB-encoded.
- **ΔE2000**: both images to CIE XYZ (sRGB → XYZ), divided by the reference's white
  ``Y_w`` (the 99th percentile of the reference's Y, so a visible lamp does not push the
  rest to black), to CIELAB (D65 white) and CIEDE2000 per pixel
  (``colour.delta_E(…, method="CIE 2000")``); the mean over pixels is reported.
- **Relative error**: ``Σ|render − reference| / Σ|reference|`` over all pixels and
  channels (one number per image; robust to black pixels).
- **SAM** (spectral renders only): mean spectral angle in degrees to the reference
  spectrum over pixels whose reference is non-zero.

References
----------
- Sharma, G., Wu, W. & Dalal, E. N. (2005). The CIEDE2000 color-difference formula.
  Color Research & Application 30(1).
"""

from __future__ import annotations

import numpy as np

from mehs.rgb import linear_sRGB_to_XYZ

DIFF_GAIN = 5.0


def white_Y(reference_rgb: np.ndarray) -> float:
    """The reference white ``Y_w``: 99th percentile of the reference's luminance (> 0)."""
    y = linear_sRGB_to_XYZ(np.asarray(reference_rgb, np.float64))[..., 1]
    w = float(np.percentile(y, 99.0)) if y.size else 0.0
    return w if w > 0 else max(float(y.max()) if y.size else 0.0, 1e-12)


def delta_E2000(rgb: np.ndarray, reference_rgb: np.ndarray, y_white: float | None = None
                ) -> np.ndarray:
    """Per-pixel CIEDE2000 ``(H, W)`` between two linear-sRGB images."""
    import colour

    yw = white_Y(reference_rgb) if y_white is None else float(y_white)
    wp = colour.CCS_ILLUMINANTS["CIE 1931 2 Degree Standard Observer"]["D65"]
    lab = [colour.XYZ_to_Lab(linear_sRGB_to_XYZ(np.asarray(x, np.float64)) / yw, wp)
           for x in (rgb, reference_rgb)]
    return np.asarray(colour.delta_E(lab[0], lab[1], method="CIE 2000"), dtype=np.float64)


def relative_error(rgb: np.ndarray, reference_rgb: np.ndarray) -> float:
    """``Σ|rgb − ref| / Σ|ref|`` over all pixels and channels."""
    den = float(np.abs(reference_rgb).sum())
    return float(np.abs(np.asarray(rgb, np.float64) - reference_rgb).sum() / den) if den > 0 else float("nan")


def spectral_angle_deg(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Angle in degrees between spectra ``(..., B)``; NaN where either is zero."""
    a = np.asarray(a, np.float64)
    b = np.asarray(b, np.float64)
    na, nb = np.linalg.norm(a, axis=-1), np.linalg.norm(b, axis=-1)
    with np.errstate(invalid="ignore", divide="ignore"):
        cos = np.sum(a * b, axis=-1) / (na * nb)
    out = np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))
    return np.where((na > 0) & (nb > 0), out, np.nan)


def difference_image(rgb: np.ndarray, reference_rgb: np.ndarray, gain: float = DIFF_GAIN
                     ) -> np.ndarray:
    """``|rgb − reference| × gain`` ``(H, W, 3)`` float32 (linear)."""
    return (np.abs(np.asarray(rgb, np.float32) - reference_rgb) * np.float32(gain)).astype(np.float32)


def score(rgb: np.ndarray, reference_rgb: np.ndarray, spectra: np.ndarray | None = None,
          reference_spectra: np.ndarray | None = None) -> dict:
    """Mean ΔE2000, relative error and (when spectra are given) mean SAM in degrees."""
    de = delta_E2000(rgb, reference_rgb)
    out = {"mean_delta_E2000": float(np.mean(de)), "relative_error": relative_error(rgb, reference_rgb)}
    if spectra is not None and reference_spectra is not None:
        sam = spectral_angle_deg(spectra, reference_spectra)
        out["mean_sam_deg"] = float(np.nanmean(sam)) if np.isfinite(sam).any() else None
    return out
