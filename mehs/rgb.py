"""Spectra → CIE XYZ → linear sRGB, as in the paper's pseudo-HDR-RGB (§3.1).

The XYZ scale constant is ``k = 1 / Σ_i ȳ(λ_i) Δλ_i`` over the cube's own band
centres (``Δλ_i`` each band's width; for evenly spaced bands it cancels, leaving the
paper's ``1 / Σ ȳ(λ_i)``), so a flat spectrum of value 1 has ``Y = 1`` whatever the
band set.
:func:`spectra_to_XYZ` is the one XYZ function of the toolkit: the pseudo-RGB
images and the SSR luminance restoration both use it, so their ``X+Y+Z`` agree.

The RGB pair of a scene: :func:`hdr_rgb` (pseudo-HDR-RGB, linear, unclipped
above, stored as half-float EXR) and :func:`ldr_rgb` (average-metered so the
log-average luminance maps to 18 % grey, clipped, sRGB-encoded, 8-bit).

References
----------
- CIE 015:2018 Colorimetry, 4th edition (CIE 1931 2° standard observer).
- IEC 61966-2-1:1999 sRGB (the matrix below, D65 white).
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np

from mehs.errors import InputError

CMFS_NAME = "CIE 1931 2 Degree Standard Observer"

#: XYZ → linear sRGB (D65): IEC 61966-2-1 (the matrix colour-science uses for sRGB).
#: The paper (and design.md §4) print the last entry as 1.0507, a transposition
#: of the standard's 1.0570: with 1.0507 a D65 white renders with B = 0.993·Y
#: and no longer agrees with colour-science. See docs/science.md "RGB pairs".
XYZ_TO_SRGB = np.array([[3.2406, -1.5372, -0.4986],
                        [-0.9689, 1.8758, 0.0415],
                        [0.0557, -0.2040, 1.0570]])

#: The matrix exactly as printed in the paper (last entry 1.0507), kept for
#: reproducing numbers computed with it; not used by mehs.
XYZ_TO_SRGB_AS_PRINTED = np.array([[3.2406, -1.5372, -0.4986],
                                   [-0.9689, 1.8758, 0.0415],
                                   [0.0557, -0.2040, 1.0507]])

#: The 31 target bands of the ME HS set: 400, 410, …, 700 nm.
WAVELENGTHS_31 = np.arange(400.0, 701.0, 10.0)


@lru_cache(maxsize=32)
def _cmfs_at(wl_key: tuple[float, ...]) -> np.ndarray:
    import colour

    cmfs = colour.MSDS_CMFS[CMFS_NAME]
    wl = np.asarray(wl_key)
    lo, hi = cmfs.wavelengths[0], cmfs.wavelengths[-1]
    if wl.min() < lo or wl.max() > hi:
        raise InputError(
            f"wavelengths {wl.min():.1f}..{wl.max():.1f} nm fall outside the "
            f"CIE 1931 2° tables ({lo:.0f}..{hi:.0f} nm)")
    # The tables are at 1 nm, so integer band centres are read exactly.
    out = np.stack([np.interp(wl, cmfs.wavelengths, cmfs.values[:, c])
                    for c in range(3)], axis=1)
    out.setflags(write=False)
    return out


def cmfs_matrix(wavelengths: np.ndarray) -> np.ndarray:
    """Scaled colour-matching matrix ``M`` of shape ``(bands, 3)`` so that ``XYZ = S @ M``.

    ``M = k · [x̄ ȳ z̄](λ_i) · Δλ_i`` with ``k = 1 / Σ ȳ(λ_i) Δλ_i``: the rectangle rule of
    colour-science's ``sd_to_XYZ(method="Integration")``, with each band's width
    ``Δλ_i`` half the distance between its neighbours (:func:`band_widths`). Evenly
    spaced bands (the 31 of the dataset) all have one width, which cancels in ``k``:
    then ``M = [x̄ ȳ z̄] / Σ ȳ``, the paper's sum. Uneven bands (a Specim IQ's centres
    are 2.88–2.99 nm apart) need the widths, or the densely sampled parts of the
    spectrum count for more: a D65 white measured there came out 0.9 ΔE00 off.
    """
    wl = np.asarray(wavelengths, dtype=np.float64).reshape(-1)
    cmf = _cmfs_at(tuple(wl.tolist()))
    dw = band_widths(wl)
    if dw is not None:
        cmf = cmf * dw[:, None]
    return cmf / cmf[:, 1].sum()


def band_widths(wavelengths: np.ndarray) -> np.ndarray | None:
    """Each band's share of the spectrum in nm, shape ``(bands,)``, in the given order;
    None when the bands are evenly spaced (to 1e-6 of the step) or fewer than three.

    Interior bands get half the distance between their neighbours, the two end bands
    the distance to their one neighbour (``np.gradient`` of the sorted centres).
    """
    wl = np.asarray(wavelengths, dtype=np.float64).reshape(-1)
    if wl.size < 3:
        return None
    order = np.argsort(wl, kind="stable")
    srt = wl[order]
    step = np.diff(srt)
    if np.all(np.abs(step - step.mean()) <= 1e-6 * abs(step.mean())):
        return None
    dw = np.empty_like(wl)
    dw[order] = np.gradient(srt)
    return dw


def spectra_to_XYZ(spectra: np.ndarray, wavelengths: np.ndarray) -> np.ndarray:
    """CIE XYZ of spectra.

    Parameters
    ----------
    spectra
        Array of shape ``(..., bands)``.
    wavelengths
        Band centres in nm, shape ``(bands,)``.

    Returns
    -------
    ndarray
        Shape ``(..., 3)``, float32 for float32 input, float64 otherwise.
    """
    spectra = np.asarray(spectra)
    wl = np.asarray(wavelengths, dtype=np.float64).reshape(-1)
    if spectra.shape[-1] != wl.size:
        raise InputError(
            f"spectra have {spectra.shape[-1]} bands but {wl.size} wavelengths were given")
    dtype = np.float32 if spectra.dtype == np.float32 else np.float64
    return spectra.astype(dtype, copy=False) @ cmfs_matrix(wl).astype(dtype)


def XYZ_to_linear_sRGB(XYZ: np.ndarray, clip_negative: bool = True) -> np.ndarray:
    """Linear sRGB from XYZ with the paper's matrix; negatives clipped to 0 by default."""
    XYZ = np.asarray(XYZ)
    dtype = np.float32 if XYZ.dtype == np.float32 else np.float64
    rgb = XYZ @ XYZ_TO_SRGB.T.astype(dtype)
    if clip_negative:
        np.maximum(rgb, 0, out=rgb)
    return rgb


def spectra_to_linear_sRGB(spectra: np.ndarray, wavelengths: np.ndarray,
                           clip_negative: bool = True) -> np.ndarray:
    """Pseudo-HDR-RGB: spectra ``(..., bands)`` → linear sRGB ``(..., 3)``, unnormalised."""
    return XYZ_to_linear_sRGB(spectra_to_XYZ(spectra, wavelengths), clip_negative)


def linear_sRGB_to_XYZ(rgb: np.ndarray) -> np.ndarray:
    """Inverse of the paper's matrix: linear sRGB ``(..., 3)`` → XYZ ``(..., 3)``."""
    rgb = np.asarray(rgb)
    dtype = np.float32 if rgb.dtype == np.float32 else np.float64
    return rgb @ np.linalg.inv(XYZ_TO_SRGB).T.astype(dtype)


# --------------------------------------------------------------------------- RGB pairs

#: Default LDR exposure rule: the log-average luminance maps to this grey (Reinhard's key).
LDR_KEY = 0.18

#: The exposure rule in words, recorded in dataset manifests.
LDR_EXPOSURE_RULE = ("exposure = 0.18 / exp(mean(ln Y)) over pixels with Y > 0 "
                     "(average metering: the log-average luminance maps to 18 % grey)")

#: Lines of a cube converted per chunk in :func:`hdr_rgb` (bounds float32 temporaries).
_RGB_CHUNK_PIXELS = 1 << 20


def luminance(rgb: np.ndarray) -> np.ndarray:
    """CIE Y of linear sRGB ``(..., 3)`` → ``(...)``, the Y row of ``inv(XYZ_TO_SRGB)``."""
    rgb = np.asarray(rgb)
    dtype = np.float32 if rgb.dtype == np.float32 else np.float64
    return rgb @ np.linalg.inv(XYZ_TO_SRGB)[1].astype(dtype)


def hdr_rgb(spectra, wavelengths=None) -> np.ndarray:
    """Pseudo-HDR-RGB of a hyperspectral image (paper §3.1, four steps).

    (1) XYZ with the CIE 1931 2° CMFs sampled at the band centres and
    ``k = 1/Σȳ`` (:func:`spectra_to_XYZ`); (2) linear sRGB with
    :data:`XYZ_TO_SRGB`; (3) negatives clipped to 0; (4) is the caller's:
    store as half-float EXR (:func:`mehs.io.exr.write_exr_rgb`). No
    normalisation, no quantisation: values above 1 are kept.

    Parameters
    ----------
    spectra
        ``(H, W, B)`` array/memmap of radiance, or a
        :class:`~mehs.cube.SpectralCube` (then ``wavelengths`` may be omitted).
    wavelengths
        Band centres in nm, ``(B,)``, inside the CMF table (360–830 nm).

    Returns
    -------
    ndarray
        float32 ``(H, W, 3)`` linear sRGB.

    Raises
    ------
    InputError
        Band/wavelength mismatch, bands outside the CMF table, NaN/Inf input.
    """
    from mehs.cube import SpectralCube

    source = None
    if isinstance(spectra, SpectralCube):
        source = spectra.source
        if wavelengths is None:
            wavelengths = spectra.wavelengths
        spectra = spectra.data
    if wavelengths is None:
        raise InputError("hdr_rgb needs the wavelengths of the bands")
    if np.ndim(spectra) != 3:
        raise InputError(f"hdr_rgb expects (H, W, bands), got shape {np.shape(spectra)}", source)
    wl = np.asarray(wavelengths, dtype=np.float64).reshape(-1)
    h, w, b = spectra.shape
    if b != wl.size:
        raise InputError(f"spectra have {b} bands but {wl.size} wavelengths were given", source)
    try:
        cmf = cmfs_matrix(wl)
    except InputError as exc:  # e.g. bands outside 360–830 nm: say which file
        raise exc.with_path(source) from None
    m = (cmf @ XYZ_TO_SRGB.T).astype(np.float32)  # (B, 3): steps 1+2 fused
    out = np.empty((h, w, 3), dtype=np.float32)
    step = max(1, _RGB_CHUNK_PIXELS // max(1, w))
    # ENVI bil/bsq memmaps are transposed views (samples fastest): multiply
    # band-major there so BLAS runs on them without a copy.
    band_major = w > 1 and spectra.strides[2] > spectra.strides[1]
    for r0 in range(0, h, step):
        block = np.asarray(spectra[r0:r0 + step])
        if band_major:
            block = block.transpose(0, 2, 1)
        if block.dtype != np.float32:
            block = block.astype(np.float32)
        if band_major:
            out[r0:r0 + step] = np.matmul(m.T, block).transpose(0, 2, 1)
        else:
            np.matmul(block, m, out=out[r0:r0 + step])
    if not np.isfinite(out).all():
        raise InputError("the spectra hold NaN/Inf values", source)
    np.maximum(out, 0, out=out)
    return out


def ldr_exposure(hdr: np.ndarray, key: float = LDR_KEY) -> float:
    """The automatic LDR exposure: ``key / exp(mean(ln Y))`` (average metering).

    The log-average luminance of the positive pixels maps to ``key`` (18 %
    grey by default), as a camera's average metering or Reinhard's key does.
    A percentile rule would let a directly visible light source — which is
    what makes these scenes HDR — set the exposure and turn the rest of the
    picture black; the log-average barely moves when a small lamp is added,
    so the diffuse scene is exposed normally and the lamp clips, as in an
    ordinary photograph. An image with no positive luminance gets exposure 1.0.
    NaN/Inf pixels or a non-positive ``key`` raise :class:`InputError`.

    References
    ----------
    Reinhard, E., Stark, M., Shirley, P., Ferwerda, J. (2002). Photographic
    tone reproduction for digital images. ACM TOG 21(3), eq. 1.
    """
    key = float(key)
    if not (np.isfinite(key) and key > 0):
        raise InputError(f"the LDR key (grey level of the log-average) must be a positive "
                         f"number, got {key}")
    hdr = np.asarray(hdr, dtype=np.float32)
    if not np.isfinite(hdr).all():
        # NaN pixels dropped out of "Y > 0" silently and one Inf gave exposure 0 (black)
        raise InputError("the HDR image holds NaN/Inf values; no exposure can be metered")
    y = luminance(hdr).ravel()
    y = y[y > 0]
    if y.size == 0:
        return 1.0
    log_avg = float(np.exp(np.mean(np.log(y.astype(np.float64)))))
    return float(key) / log_avg if log_avg > 0 else 1.0


def srgb_encode_uint8(linear: np.ndarray) -> np.ndarray:
    """Clip linear values to [0, 1], apply the sRGB OETF (IEC 61966-2-1) and round to uint8."""
    import colour

    x = np.clip(np.asarray(linear, dtype=np.float64), 0.0, 1.0)
    v = colour.cctf_encoding(x, function="sRGB")
    return np.rint(np.asarray(v) * 255.0).astype(np.uint8)


def ldr_rgb(hdr: np.ndarray, *, exposure: float | None = None,
            key: float = LDR_KEY) -> tuple[np.ndarray, float]:
    """LDR-RGB of a pseudo-HDR-RGB image: expose, clip, sRGB-encode, quantise.

    Exposure rule: ``exposure`` when given, else :func:`ldr_exposure` —
    the log-average luminance maps to ``key`` (18 % grey), so the diffuse
    scene is exposed like an ordinary photograph and light sources clip. Then ``clip(exposure · hdr, 0, 1)``, the
    sRGB OETF (``colour.cctf_encoding(…, "sRGB")``) and ``rint(255 · v)``.

    Parameters
    ----------
    hdr
        Linear sRGB ``(H, W, 3)``, e.g. from :func:`hdr_rgb`.
    exposure
        Multiplier applied before clipping; ``None`` for the automatic rule.
    key
        Grey level the log-average luminance maps to under the automatic rule.

    Returns
    -------
    (ndarray, float)
        uint8 ``(H, W, 3)`` sRGB-encoded image and the exposure used.

    Raises
    ------
    InputError
        Wrong shape, NaN/Inf, or a non-positive/non-finite exposure.
    """
    hdr = np.asarray(hdr)
    if hdr.ndim != 3 or hdr.shape[2] != 3:
        raise InputError(f"ldr_rgb expects (H, W, 3), got shape {hdr.shape}")
    if not np.isfinite(hdr).all():
        raise InputError("the HDR image holds NaN/Inf values")
    if exposure is None:
        exposure = ldr_exposure(hdr, key)
    exposure = float(exposure)
    if not (np.isfinite(exposure) and exposure > 0):
        raise InputError(f"exposure must be a positive number, got {exposure}")
    return srgb_encode_uint8(hdr.astype(np.float32) * np.float32(exposure)), exposure
