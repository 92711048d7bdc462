"""Tone-mapped previews (8-bit sRGB PNG) of HDR-RGB and HDR-HS images.

Previews are for eyes and reports only — never for metrics. The default
operator is Reinhard et al. 2002's *global* photographic operator:

1. world luminance ``L_w = Y`` of linear sRGB (:func:`mehs.rgb.luminance`);
2. log-average ``L̄_w = exp(mean(log(δ + L_w)))`` over pixels with
   ``L_w > 0`` (δ = 1e-6 · max L_w guards log 0);
3. scaled luminance ``L = key / L̄_w · L_w`` (``key`` = 0.18, "middle grey");
4. ``L_d = L (1 + L / L_white²) / (1 + L)`` with ``L_white`` the smallest
   scaled luminance mapped to white — by default the largest ``L`` in the
   image (Reinhard's choice: nothing burns out); ``inf`` gives ``L/(1+L)``;
5. colour kept by scaling RGB by ``L_d / L_w``, then clip to [0, 1], sRGB
   OETF, round to uint8.

References
----------
- Reinhard, E., Stark, M., Shirley, P., & Ferwerda, J. (2002). Photographic
  tone reproduction for digital images. ACM Transactions on Graphics 21(3),
  267–276 (equations 1, 2 and 4).
"""

from __future__ import annotations

from pathlib import Path
from typing import Callable

import numpy as np

from mehs.errors import FormatError, InputError
from mehs.io.atomic import write_bytes_atomic
from mehs.rgb import ldr_rgb, luminance, srgb_encode_uint8

#: Visible range a cube must cover for a colorimetric preview (nm).
VISIBLE_NM = (400.0, 700.0)

#: Band centres used for a false-colour preview when no default bands are set.
FALLBACK_RGB_NM = (640.0, 550.0, 460.0)


def tonemap_Reinhard2002(rgb: np.ndarray, *, key: float = 0.18,
                         white: float | None = None) -> np.ndarray:
    """Reinhard 2002 global operator on linear RGB ``(H, W, 3)`` → uint8 sRGB ``(H, W, 3)``.

    Parameters
    ----------
    key
        The key value ``a`` (0.18 for a normal-key scene; 0.09 low, 0.36 high).
    white
        ``L_white`` in scaled-luminance units; ``None``: the image's maximum
        scaled luminance; ``float("inf")``: plain ``L / (1 + L)``.
    """
    rgb = _check_rgb(rgb)
    if not key > 0:
        raise InputError(f"the tone-mapping key must be positive, got {key}")
    lw = luminance(rgb)
    pos = lw > 0
    if not pos.any():
        return np.zeros(rgb.shape, np.uint8)
    delta = 1e-6 * float(lw.max())
    log_avg = float(np.exp(np.mean(np.log(delta + lw[pos], dtype=np.float64))))
    scaled = lw * np.float32(key / log_avg)
    l_white = float(scaled.max()) if white is None else float(white)
    if not l_white > 0:
        raise InputError(f"the white point must be positive, got {white}")
    ld = scaled * (1.0 + scaled / np.float32(l_white ** 2)) / (1.0 + scaled) \
        if np.isfinite(l_white) else scaled / (1.0 + scaled)
    ratio = np.divide(ld, lw, out=np.zeros_like(lw), where=pos)
    return srgb_encode_uint8(rgb * ratio[..., None])


def tonemap_exposure(rgb: np.ndarray, *, exposure: float | None = None) -> np.ndarray:
    """The LDR-RGB rule (:func:`mehs.rgb.ldr_rgb`): expose, clip, sRGB-encode."""
    return ldr_rgb(_check_rgb(rgb), exposure=exposure)[0]


#: Tone-mapping operators: name → ``f(rgb (H, W, 3), **kwargs) -> uint8 (H, W, 3)``.
TONEMAP_METHODS: dict[str, Callable[..., np.ndarray]] = {
    "reinhard": tonemap_Reinhard2002,
    "Reinhard2002": tonemap_Reinhard2002,
    "exposure": tonemap_exposure,
}


def tonemap(rgb: np.ndarray, method: str = "reinhard", **kwargs) -> np.ndarray:
    """Tone-map linear RGB ``(H, W, 3)`` to uint8 sRGB ``(H, W, 3)`` with a :data:`TONEMAP_METHODS` operator."""
    if method not in TONEMAP_METHODS:
        raise InputError(f"unknown tone-mapping method {method!r}; "
                         f"choose one of {sorted(TONEMAP_METHODS)}")
    return TONEMAP_METHODS[method](rgb, **kwargs)


def _check_rgb(rgb: np.ndarray) -> np.ndarray:
    rgb = np.asarray(rgb)
    if rgb.ndim != 3 or rgb.shape[2] != 3:
        raise InputError(f"expected an RGB image (H, W, 3), got shape {rgb.shape}")
    rgb = rgb.astype(np.float32, copy=False)
    if not np.isfinite(rgb).all():
        raise InputError("the image holds NaN/Inf values")
    return np.maximum(rgb, 0)


def preview_rgb(cube) -> np.ndarray:
    """Linear RGB ``(H, W, 3)`` float32 to show for a cube.

    Colorimetric (:func:`mehs.rgb.hdr_rgb` over the bands inside the CMF table)
    when the bands cover 400–700 nm; otherwise a false-colour stack of the
    cube's ``default_bands`` (or the bands nearest 640/550/460 nm).
    """
    from mehs.rgb import hdr_rgb

    wl = cube.wavelengths
    tol = 10.0
    if wl[0] <= VISIBLE_NM[0] + tol and wl[-1] >= VISIBLE_NM[1] - tol:
        sel = np.flatnonzero((wl >= 360.0) & (wl <= 830.0))
        data = cube.data if sel.size == wl.size else \
            cube.data[:, :, int(sel[0]):int(sel[-1]) + 1]
        return hdr_rgb(data, wl[sel[0]:sel[-1] + 1])
    bands = cube.default_bands or tuple(cube.band_index(w) for w in FALLBACK_RGB_NM)
    rgb = np.stack([np.asarray(cube.data[:, :, b], dtype=np.float32) for b in bands], axis=2)
    if not np.isfinite(rgb).all():
        raise InputError("the cube holds NaN/Inf values", cube.source)
    return np.maximum(rgb, 0)


def hs_preview(cube, method: str = "reinhard", **kwargs) -> np.ndarray:
    """Tone-mapped uint8 sRGB ``(lines, samples, 3)`` preview of a spectral cube (see :func:`preview_rgb`)."""
    return tonemap(preview_rgb(cube), method, **kwargs)


def write_png(path: str | Path, img: np.ndarray) -> Path:
    """Write an 8/16-bit RGB ``(H, W, 3)`` or gray ``(H, W)`` image as PNG, atomically.

    ``img`` is RGB order (OpenCV's BGR swap is done here); dtype uint8 or uint16.
    """
    import cv2

    path = Path(path)
    img = np.asarray(img)
    if img.dtype not in (np.uint8, np.uint16):
        raise InputError(f"PNG needs uint8 or uint16 pixels, got {img.dtype}", path)
    if img.ndim == 3 and img.shape[2] == 1:
        img = img[:, :, 0]
    if img.ndim == 3 and img.shape[2] in (3, 4):
        img = img[:, :, [2, 1, 0] + ([3] if img.shape[2] == 4 else [])]
    elif img.ndim != 2:
        raise InputError(f"PNG needs (H, W), (H, W, 3) or (H, W, 4), got shape {img.shape}", path)
    ok, buf = cv2.imencode(".png", np.ascontiguousarray(img))
    if not ok:
        raise FormatError("OpenCV could not encode the PNG", path)
    return write_bytes_atomic(path, buf.tobytes())


def read_png(path: str | Path) -> np.ndarray:
    """Read a PNG as stored: uint8/uint16 ``(H, W)`` gray or ``(H, W, 3|4)`` in RGB(A) order."""
    import cv2

    path = Path(path)
    if not path.is_file():
        raise InputError("file does not exist", path)
    img = cv2.imdecode(np.fromfile(path, dtype=np.uint8), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise FormatError("not a readable PNG image", path)
    if img.ndim == 3 and img.shape[2] in (3, 4):
        img = img[:, :, [2, 1, 0] + ([3] if img.shape[2] == 4 else [])]
    return np.ascontiguousarray(img)
