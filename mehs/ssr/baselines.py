"""Baseline SSR models: Smits 1999, Mallett & Yuksel 2019, root-polynomial regression.

All work on whole images ``(H, W, 3)`` at once and return ``(H, W, 31)`` on
400:700:10 nm (:data:`mehs.rgb.WAVELENGTHS_31`).

Smits 1999
    colour-science's per-pixel :func:`colour.recovery.RGB_to_sd_Smits1999`
    combines seven basis spectra (white, cyan, magenta, yellow, red, green,
    blue) given at 10 bins from 380 to 720 nm (37.8 nm apart). The result is a
    :class:`colour.SpectralDistribution` with a *linear* interpolator, so we
    resample each basis spectrum to 400:700:10 by that same interpolator
    (``sd[WAVELENGTHS_31]``, identical to
    ``sd.copy().align(SpectralShape(400, 700, 10))`` for this non-uniform
    grid). Because the method is linear in the basis given the ordering of
    R, G, B, the vectorised form is: ``min·white + (mid − min)·secondary(argmin)
    + (max − mid)·primary(argmax)`` where the secondary is cyan/magenta/yellow
    for min = R/G/B. Ties give zero weights, so which branch colour takes on a
    tie does not matter. colour neither clamps nor normalises its input: values
    above 1 (HDR) scale the spectrum linearly and negatives go through the same
    branches; we do the same, so the result is exposure-equivariant
    (``f(k·rgb) = k·f(rgb)`` for k > 0). Input is the linear sRGB of the
    dataset, used as colour's Smits RGB (sRGB primaries, E white) as in the paper.
Mallett & Yuksel 2019
    ``spectrum = rgb @ B`` with colour's
    :data:`colour.recovery.MSDS_BASIS_FUNCTIONS_sRGB_MALLETT2019` (tabulated at
    5 nm, so read exactly at 400:700:10). Linear, hence exposure-equivariant.
Root-polynomial regression (Lin & Finlayson)
    ``spectrum = φ(rgb) @ M`` with root-polynomial terms of degree d (d = 2:
    r, g, b, √(rg), √(gb), √(rb); d = 3 adds the 7 cube-root terms). Every term
    is homogeneous of degree 1, so the model is exposure-invariant in shape and
    equivariant in scale. ``M`` is fitted by ridge-regularised least squares on
    pixels sampled from a dataset's training split. Negative RGB is clipped to 0
    before the roots. Two targets:

    - ``"spectra"`` (linear input, no pre-processing): each training pair is
      divided by its ``r + g + b`` so that bright HDR pixels do not dominate the
      fit (the fit targets relative error, as MRAE does); the model predicts
      absolute spectra (restoration optional).
    - ``"shape"`` (the default with pre-processing, the paper's spectral
      similarity, §3.3): the input is divided by its own ``r + g + b`` and the
      spectrum by its own ``X + Y + Z``; the model predicts a shape, always
      luminance-restored. On Reinhard input the absolute target is ill-posed:
      ``x/(1+x)`` compresses and the per-image key removes the exposure, so
      spectra divided by the tone-mapped ``r + g + b`` spanned three decades in
      the demo (3 to 3077 on one scene), the least squares followed the
      brightest pixels with cancelling coefficients (±300) and the predicted
      shapes had ``X+Y+Z ≤ 0`` on 74 % of the test pixels (restoration fell back
      to a flat spectrum there). Fitting the shape leaves nothing to fit but the
      chromaticity → shape map.

References
----------
- Smits, B. (1999). An RGB-to-Spectrum Conversion for Reflectances. Journal of
  Graphics Tools 4(4), 11–22.
- Mallett, I., Yuksel, C. (2019). Spectral Primary Decomposition for Rendering
  with sRGB Reflectance. EGSR (DL-only/industry track).
- Lin, Y.-T., Finlayson, G. D. (2019). Exposure invariance in spectral
  reconstruction from RGB images. Color and Imaging Conference 27, 284–289.
- Lin, Y.-T., Finlayson, G. D. (2020). Physically plausible spectral
  reconstruction. Sensors 20(21), 6399.
- Finlayson, G. D., Mackiewicz, M., Hurlbert, A. (2015). Color correction using
  root-polynomial regression. IEEE TIP 24(5), 1460–1470.
"""

from __future__ import annotations

import json
import zipfile
from functools import lru_cache
from pathlib import Path
from typing import Any, Iterable

import numpy as np

from mehs._blas import single_thread_blas
from mehs.errors import FormatError, InputError
from mehs.rgb import WAVELENGTHS_31
from mehs.ssr.contract import SSRModel, TrainedFor
from mehs.ssr.preprocess import Preprocessing
from mehs.ssr.registry import register_model

SMITS_BASIS_ORDER = ("white", "cyan", "magenta", "yellow", "red", "green", "blue")


@lru_cache(maxsize=8)
def _smits_basis(wl_key: tuple[float, ...]) -> np.ndarray:
    from colour.recovery import SDS_SMITS1999

    wl = np.asarray(wl_key)
    basis = np.stack([np.asarray(SDS_SMITS1999[k][wl], dtype=np.float64)
                      for k in SMITS_BASIS_ORDER])
    basis.setflags(write=False)
    return basis


def smits_basis(wavelengths: np.ndarray = WAVELENGTHS_31) -> np.ndarray:
    """The 7 Smits basis spectra (white, cyan, magenta, yellow, red, green, blue), ``(7, B)``."""
    return _smits_basis(tuple(np.asarray(wavelengths, dtype=np.float64).tolist()))


#: Pixels per block in the vectorised Smits (keeps the temporaries in cache).
_SMITS_CHUNK = 1 << 15


def _smits_coefficients_into(x: np.ndarray, coef: np.ndarray) -> None:
    """Fill ``coef (n, 7)`` with the Smits basis weights of ``x (n, 3)``.

    ``min·white + (mid − min)·secondary(argmin) + (max − mid)·primary(argmax)``.
    A tie sets two indicator columns, but then its weight (mid − min or
    max − mid) is 0, so the sum is the same whichever branch colour takes.
    """
    r, g, b = x[:, 0], x[:, 1], x[:, 2]
    lo = np.minimum(np.minimum(r, g), b)
    hi = np.maximum(np.maximum(r, g), b)
    mid = np.maximum(np.minimum(r, g), np.minimum(np.maximum(r, g), b))  # exact median
    d1 = mid - lo
    d2 = hi - mid
    coef[:, 0] = lo
    for j, ch in enumerate((r, g, b)):
        np.multiply(d1, ch == lo, out=coef[:, 1 + j])   # cyan, magenta, yellow
        np.multiply(d2, ch == hi, out=coef[:, 4 + j])   # red, green, blue


def smits_coefficients(rgb: np.ndarray) -> np.ndarray:
    """Weights of the 7 Smits basis spectra per pixel: ``(..., 3) → (..., 7)`` float32/64."""
    rgb = np.asarray(rgb)
    dtype = np.float32 if rgb.dtype == np.float32 else np.float64
    flat = rgb.reshape(-1, 3).astype(dtype, copy=False)
    coef = np.empty((flat.shape[0], 7), dtype=dtype)
    _smits_coefficients_into(flat, coef)
    return coef.reshape(*rgb.shape[:-1], 7)


def RGB_to_spectra_Smits1999(rgb: np.ndarray,
                             wavelengths: np.ndarray = WAVELENGTHS_31) -> np.ndarray:
    """Smits (1999) spectra of linear RGB, vectorised: ``(..., 3) → (..., B)``.

    Agrees with ``colour.recovery.RGB_to_sd_Smits1999(rgb)[wavelengths]`` per
    pixel (see the module notes). float32 in → float32 out. Processed in blocks
    of :data:`_SMITS_CHUNK` pixels written straight into the output.
    """
    rgb = np.asarray(rgb)
    if rgb.shape[-1] != 3:
        raise InputError(f"Smits 1999 needs (..., 3) RGB, got shape {rgb.shape}")
    dtype = np.float32 if rgb.dtype == np.float32 else np.float64
    flat = rgb.reshape(-1, 3).astype(dtype, copy=False)
    basis = smits_basis(wavelengths).astype(dtype)
    n = flat.shape[0]
    out = np.empty((n, basis.shape[1]), dtype=dtype)
    coef = np.empty((min(n, _SMITS_CHUNK), 7), dtype=dtype)
    with single_thread_blas():  # small memory-bound products: see mehs._blas
        for s in range(0, n, _SMITS_CHUNK):
            x = flat[s:s + _SMITS_CHUNK]
            c = coef[:x.shape[0]]
            _smits_coefficients_into(x, c)
            np.matmul(c, basis, out=out[s:s + x.shape[0]])
    return out.reshape(*rgb.shape[:-1], basis.shape[1])


@lru_cache(maxsize=8)
def _mallett_basis(wl_key: tuple[float, ...]) -> np.ndarray:
    from colour.recovery import MSDS_BASIS_FUNCTIONS_sRGB_MALLETT2019 as msds

    wl = np.asarray(wl_key)
    basis = np.asarray(msds[wl], dtype=np.float64).T  # (3, B)
    basis.setflags(write=False)
    return basis


def mallett_basis(wavelengths: np.ndarray = WAVELENGTHS_31) -> np.ndarray:
    """Mallett & Yuksel (2019) sRGB basis (red, green, blue) at ``wavelengths``, ``(3, B)``."""
    return _mallett_basis(tuple(np.asarray(wavelengths, dtype=np.float64).tolist()))


def RGB_to_spectra_Mallett2019(rgb: np.ndarray,
                               wavelengths: np.ndarray = WAVELENGTHS_31) -> np.ndarray:
    """Mallett & Yuksel (2019) spectra of linear sRGB: one matrix product ``(..., 3) → (..., B)``."""
    rgb = np.asarray(rgb)
    if rgb.shape[-1] != 3:
        raise InputError(f"Mallett 2019 needs (..., 3) RGB, got shape {rgb.shape}")
    dtype = np.float32 if rgb.dtype == np.float32 else np.float64
    with single_thread_blas():  # a (pixels, 3) @ (3, B) product is memory-bound
        return rgb.astype(dtype, copy=False) @ mallett_basis(wavelengths).astype(dtype)


def root_polynomial_features(rgb: np.ndarray, degree: int = 2) -> np.ndarray:
    """Root-polynomial terms of linear RGB: ``(..., 3) → (..., F)``, F = 3, 6 or 13 for degree 1, 2, 3.

    Order: r, g, b; √(rg), √(gb), √(rb); ∛(rg²), ∛(gb²), ∛(rb²), ∛(gr²), ∛(bg²), ∛(br²), ∛(rgb).
    """
    rgb = np.asarray(rgb)
    dtype = np.float32 if rgb.dtype == np.float32 else np.float64
    x = np.maximum(rgb.astype(dtype, copy=False), 0)
    r, g, b = x[..., 0], x[..., 1], x[..., 2]
    terms = [r, g, b]
    if degree >= 2:
        terms += [np.sqrt(r * g), np.sqrt(g * b), np.sqrt(r * b)]
    if degree >= 3:
        terms += [np.cbrt(r * g * g), np.cbrt(g * b * b), np.cbrt(r * b * b),
                  np.cbrt(g * r * r), np.cbrt(b * g * g), np.cbrt(b * r * r),
                  np.cbrt(r * g * b)]
    if degree not in (1, 2, 3):
        raise InputError(f"root-polynomial degree must be 1, 2 or 3, got {degree}")
    return np.stack(terms, axis=-1)


class _FixedBaseline(SSRModel):
    """A baseline with no trained state: a function of (rgb, wavelengths).

    Nothing was fitted, so its own setting is "no pre-processing"; the
    evaluation scores it with pre-processing only when the user asks.
    """

    trained_for = TrainedFor(input=None, preprocessing=None, output="either", fixed=True)

    def __init__(self, wavelengths: np.ndarray = WAVELENGTHS_31):
        self.wavelengths = np.asarray(wavelengths, dtype=np.float64)

    def predict(self, rgb: np.ndarray) -> np.ndarray:
        return type(self).convert(rgb, self.wavelengths)


class Smits1999(_FixedBaseline):
    """Smits (1999) RGB → spectrum, vectorised (matches colour-science per pixel)."""

    name = "smits"
    description = "Smits 1999, 7 basis spectra (colour-science tables), vectorised"
    convert = staticmethod(RGB_to_spectra_Smits1999)


class Mallett2019(_FixedBaseline):
    """Mallett & Yuksel (2019) sRGB basis, one matrix product."""

    name = "mallett"
    description = "Mallett & Yuksel 2019 sRGB basis (colour-science), one matrix product"
    convert = staticmethod(RGB_to_spectra_Mallett2019)


class RegressionModel(SSRModel):
    """Exposure-invariant root-polynomial regression ``spectrum = φ(rgb) @ M``.

    Attributes
    ----------
    matrix
        ``(F, B)`` float64 regression matrix.
    degree
        Root-polynomial degree (1, 2 or 3).
    wavelengths
        Output band centres, ``(B,)``.
    info
        Provenance of the fit (dataset, split, samples, ridge, seed, …);
        ``info["target"]`` is ``"shape"`` or ``"spectra"`` (older files: spectra).
    """

    FORMAT = "mehs-ssr-regression/1"
    description = "root-polynomial regression (Lin & Finlayson), exposure-invariant"
    #: What a fit may target (see the module notes).
    TARGETS = ("spectra", "shape")

    def __init__(self, matrix: np.ndarray, *, degree: int = 2,
                 wavelengths: np.ndarray = WAVELENGTHS_31, name: str = "regression",
                 info: dict[str, Any] | None = None):
        self.matrix = np.asarray(matrix, dtype=np.float64)
        self.degree = int(degree)
        self.wavelengths = np.asarray(wavelengths, dtype=np.float64)
        nf = root_polynomial_features(np.ones((1, 3)), self.degree).shape[-1]
        if self.matrix.shape != (nf, self.wavelengths.size):
            raise InputError(f"regression matrix shape {self.matrix.shape} does not fit degree "
                             f"{self.degree} ({nf} terms) and {self.wavelengths.size} bands")
        self.name = name
        self.info = dict(info or {})
        if self.info.get("preprocessing") and self.target == "spectra":
            # files fitted before the shape target: their shapes are often non-positive
            self.description = (f"{type(self).description}; fitted to absolute spectra on "
                                "pre-processed input, whose shapes can have X+Y+Z ≤ 0 (a "
                                "flat-spectrum fallback of the restoration): refit it with "
                                "'mehs train-baseline' to fit the shape")

    @property
    def target(self) -> str:
        """``"shape"`` or ``"spectra"``: what the fit targeted (older files: spectra)."""
        return "shape" if self.info.get("target") == "shape" else "spectra"

    @property
    def trained_for(self) -> TrainedFor:
        """Fitted on ``info["input"]`` RGB with ``info["preprocessing"]`` (older files: none);
        a shape fit is always luminance-restored, an absolute one either way."""
        inp = self.info.get("input")
        return TrainedFor(input=inp if inp in ("hdr", "ldr") else None,
                          preprocessing=Preprocessing.from_dict(self.info.get("preprocessing")),
                          output="shape" if self.target == "shape" else "either")

    def predict(self, rgb: np.ndarray) -> np.ndarray:
        phi = root_polynomial_features(rgb, self.degree)
        return phi @ self.matrix.astype(phi.dtype)

    @classmethod
    def fit(cls, rgb: np.ndarray, spectra: np.ndarray, *, degree: int = 2,
            wavelengths: np.ndarray = WAVELENGTHS_31, ridge: float = 1e-6,
            info: dict[str, Any] | None = None, target: str = "spectra") -> "RegressionModel":
        """Least-squares fit on pairs ``rgb (N, 3)``, ``spectra (N, B)``.

        ``target="spectra"``: pairs are normalised by their ``r + g + b`` (pairs
        with a non-positive or non-finite sum are dropped). ``target="shape"``:
        the RGB by its ``r + g + b`` and the spectrum by its own ``X + Y + Z``
        (:func:`mehs.ssr.luminance.xyz_sum` at ``wavelengths``; pairs where either
        is not positive are dropped), so the model predicts a spectral shape for
        luminance restoration. ``ridge`` is relative to the mean diagonal of ``ΦᵀΦ``.
        """
        if not (np.isfinite(ridge) and ridge >= 0):
            # a negative ridge can make the normal equations singular or indefinite
            raise InputError(f"ridge must be finite and >= 0, got {ridge}")
        if target not in cls.TARGETS:
            raise InputError(f"regression target must be one of {cls.TARGETS}, got {target!r}")
        rgb = np.asarray(rgb, dtype=np.float64).reshape(-1, 3)
        spectra = np.asarray(spectra, dtype=np.float64)
        spectra = spectra.reshape(-1, spectra.shape[-1])
        if rgb.shape[0] != spectra.shape[0]:
            raise InputError(f"{rgb.shape[0]} RGB samples for {spectra.shape[0]} spectra")
        s = np.maximum(rgb, 0).sum(1)
        ok = np.isfinite(s) & (s > 0) & np.all(np.isfinite(spectra), axis=1)
        if target == "shape":
            if spectra.shape[1] != np.asarray(wavelengths).size:
                raise InputError(f"spectra have {spectra.shape[1]} bands but "
                                 f"{np.asarray(wavelengths).size} wavelengths were given")
            from mehs.ssr.luminance import xyz_sum

            t = xyz_sum(np.where(ok[:, None], spectra, 0.0), wavelengths)
            ok &= np.isfinite(t) & (t > 0)
        else:
            t = s
        if np.count_nonzero(ok) < 50:
            raise InputError(f"only {np.count_nonzero(ok)} usable training pixels (need ≥ 50)")
        x = rgb[ok] / s[ok, None]
        y = spectra[ok] / t[ok, None]
        phi = root_polynomial_features(x, degree)
        ata = phi.T @ phi
        lam = ridge * np.trace(ata) / ata.shape[0]
        matrix = np.linalg.solve(ata + lam * np.eye(ata.shape[0]), phi.T @ y)
        meta = {"n_samples": int(np.count_nonzero(ok)), "ridge": ridge, **(info or {}),
                "target": target}
        return cls(matrix, degree=degree, wavelengths=wavelengths, info=meta)

    def save(self, path: str | Path) -> Path:
        """Write the model as ``.npz`` (arrays + JSON metadata) or ``.json``, atomically."""
        from mehs.io.atomic import atomic_path, write_json_atomic

        path = check_model_path(path, self.FORMAT)
        meta = {"format": self.FORMAT, "name": self.name, "degree": self.degree,
                "info": self.info}
        if path.suffix.lower() == ".json":
            return write_json_atomic(path, {**meta, "wavelengths": self.wavelengths.tolist(),
                                            "matrix": self.matrix.tolist()})
        with atomic_path(path) as tmp:
            with open(tmp, "wb") as fh:
                np.savez(fh, matrix=self.matrix, wavelengths=self.wavelengths,
                         meta=np.array(json.dumps(meta, default=str)))
        return path

    @classmethod
    def load(cls, path: str | Path) -> "RegressionModel":
        """Read a model written by :meth:`save`."""
        path = Path(path)
        if not path.is_file():
            raise InputError("no such regression model file", path)
        try:
            if path.suffix.lower() == ".json":
                d = json.loads(path.read_text())
                meta, matrix, wl = d, d["matrix"], d["wavelengths"]
            else:
                with np.load(path, allow_pickle=False) as z:
                    matrix, wl = z["matrix"], z["wavelengths"]
                    meta = json.loads(str(z["meta"]))
        except (OSError, ValueError, KeyError, EOFError, zipfile.BadZipFile) as exc:
            # an empty .npz raises EOFError, a damaged one BadZipFile: both are bad input
            raise FormatError(f"not a regression model file ({type(exc).__name__}: {exc})",
                              path) from None
        if meta.get("format") != cls.FORMAT:
            raise FormatError(f"format is {meta.get('format')!r}, expected {cls.FORMAT!r}", path)
        try:
            return cls(matrix, degree=meta["degree"], wavelengths=wl,
                       name=meta.get("name", "regression"), info=meta.get("info"))
        except InputError as exc:
            raise FormatError(exc.problem, path) from None


def check_model_path(path: str | Path, fmt: str) -> Path:
    """``path`` if a model may be written there, else :class:`InputError`.

    Only ``.json``/``.npz`` names are accepted and an existing ``.json`` is
    replaced only if it already holds a model of format ``fmt``: a mistyped
    ``--out DATASET/manifest.json`` must not destroy the dataset's manifest.
    """
    path = Path(path)
    if path.is_dir():
        raise InputError("the model must be a .json or .npz file, not a folder", path)
    if path.suffix.lower() not in (".json", ".npz"):
        raise InputError("the model file name must end in .json or .npz", path)
    if path.suffix.lower() == ".json" and path.exists():
        try:
            existing = json.loads(path.read_text(encoding="utf-8")).get("format")
        except (OSError, ValueError, AttributeError):
            existing = None
        if existing != fmt:
            raise InputError(f"exists and is not a {fmt} model; refusing to replace it", path)
    return path


def fit_regression_baseline(pairs: Iterable, *, degree: int = 2, n_samples: int = 200_000,
                            input: str = "hdr", ridge: float = 1e-6, seed: int = 0,
                            preprocessing: Preprocessing | None = None,
                            target: str | None = None,
                            progress: bool = False) -> RegressionModel:
    """Fit :class:`RegressionModel` on pixels sampled from paired scenes.

    Parameters
    ----------
    pairs
        :class:`mehs.ssr.data.Pair` objects (e.g. ``load_pairs(ds, split="train")``).
    n_samples
        Total pixels to sample, spread evenly over the scenes (valid pixels only).
    input
        ``"hdr"`` or ``"ldr"``: which RGB the baseline learns from.
    preprocessing
        Pre-processing applied to each training image before sampling (e.g.
        ``Preprocessing()``: Reinhard at key 0.18); recorded in the model, so
        the evaluation scores it only with that pre-processing.
    target
        ``"shape"`` or ``"spectra"`` (see :meth:`RegressionModel.fit`); default
        ``"shape"`` with pre-processing (tone-mapped RGB does not determine
        absolute spectra: the per-image key removes the exposure), else ``"spectra"``.
    """
    target = target or ("shape" if preprocessing is not None else "spectra")
    if target not in RegressionModel.TARGETS:  # before minutes of sampling
        raise InputError(f"regression target must be one of {RegressionModel.TARGETS}, "
                         f"got {target!r}")
    if int(n_samples) < 1:
        raise InputError(f"n_samples must be at least 1, got {n_samples}")
    if not (np.isfinite(ridge) and ridge >= 0):  # before minutes of sampling
        raise InputError(f"ridge must be finite and >= 0, got {ridge}")
    pairs = list(pairs)
    if not pairs:
        raise InputError("no training scenes to fit the regression baseline on")
    rng = np.random.default_rng(seed)
    per = max(1, int(n_samples) // len(pairs))
    xs, ys = [], []
    wl = None
    it = pairs
    if progress:
        from tqdm import tqdm
        it = tqdm(pairs, desc="sampling", unit="scene")
    for pair in it:
        cube = pair.hs()
        if wl is None:
            wl = cube.wavelengths
        elif wl.shape != cube.wavelengths.shape or not np.allclose(wl, cube.wavelengths):
            raise InputError("training scenes have different band sets", pair.hs_path)
        rgb = pair.rgb(input)
        if preprocessing is not None:
            rgb = preprocessing(rgb)
        valid = pair.valid()
        idx = np.flatnonzero(valid.reshape(-1))
        if idx.size == 0:
            continue
        take = rng.choice(idx, size=min(per, idx.size), replace=False)
        xs.append(rgb.reshape(-1, 3)[take])
        ys.append(np.asarray(cube.data).reshape(-1, cube.bands)[take])
    if not xs:
        raise InputError("no valid training pixels in the given scenes")
    info = {"input": input, "seed": seed, "scenes": [p.id for p in pairs],
            "preprocessing": None if preprocessing is None else preprocessing.to_dict()}
    return RegressionModel.fit(np.concatenate(xs), np.concatenate(ys), degree=degree,
                               wavelengths=wl, ridge=ridge, info=info, target=target)


def _regression_factory(path: str | Path | None = None, **_: Any) -> RegressionModel:
    if path is None:
        raise InputError("the regression baseline needs a fitted model: run "
                         "'mehs train-baseline DATASET --out model.npz' and pass model.npz "
                         "(mehs evaluate fits it on the dataset's train split by itself)")
    return RegressionModel.load(path)


#: Dispatcher of the RGB → spectra baseline functions (vectorised).
RECOVERY_METHODS = {
    "Smits 1999": RGB_to_spectra_Smits1999,
    "Mallett 2019": RGB_to_spectra_Mallett2019,
}

register_model("smits", Smits1999, description=Smits1999.description, overwrite=True)
register_model("mallett", Mallett2019, description=Mallett2019.description, overwrite=True)
register_model("regression", _regression_factory, description=RegressionModel.description,
               overwrite=True)
