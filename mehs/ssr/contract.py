"""The SSR model contract and the declaration of what a model was trained for.

This is the bottom of :mod:`mehs.ssr`: it imports nothing of the package but
:mod:`mehs.ssr.preprocess`. Baselines, networks, the registry, the pipeline and
the evaluation all build on it.

Contract
--------
An SSR model is any object with

- ``name: str``
- ``wavelengths: ndarray (B,)`` — the band centres (nm) of its output
- ``__call__(rgb: float32 (H, W, 3) linear) -> float32 (H, W, B)``

and, optionally,

- ``trained_for: TrainedFor`` — the input it was trained for (see below);
- ``applies_preprocessing: bool`` — it applies its declared pre-processing
  itself (a network graph), so callers pass unprocessed linear RGB;
- ``standard_spectrum(rgb) -> (H, W, B)`` — for a model whose output is a
  *shape* S (``TrainedFor.output == "shape"``) and which restores luminance
  inside ``__call__``: the unrestored S, so the evaluation can restore it
  itself and count the fallbacks.

:class:`SSRModel` is a convenience base class; duck typing is enough.

Trained-input declaration (:class:`TrainedFor`)
-----------------------------------------------
``input``
    ``"hdr"`` / ``"ldr"`` — the RGB it was fitted on; ``None`` = not fitted
    (fixed baselines) or unknown.
``preprocessing``
    The :class:`~mehs.ssr.preprocess.Preprocessing` it was trained with (scale
    included), or ``None``.
``output``
    ``"shape"``: a spectral shape to be luminance-restored (learning spectral
    similarity, ◇); ``"spectra"``: absolute spectra, end to end (never
    restored); ``"either"``: an exposure-equivariant baseline whose output is
    meaningful both ways (restoration on by default).
``fixed``
    True for models with nothing trained (Smits, Mallett): "its" pre-processing
    setting is off, and it is scored with pre-processing only if the user asks.
``declared``
    False for user callables that say nothing: scored under every requested
    setting, with a note.
"""

from __future__ import annotations

import inspect
from dataclasses import dataclass
from typing import Any, Callable, Protocol, runtime_checkable

import numpy as np

from mehs.errors import InputError
from mehs.rgb import WAVELENGTHS_31
from mehs.ssr.preprocess import PAPER_PREPROCESSING, Preprocessing

OUTPUT_KINDS = ("shape", "spectra", "either")
INPUT_KINDS = ("hdr", "ldr")


@dataclass(frozen=True)
class TrainedFor:
    """What a model was trained for (see the module notes)."""

    input: str | None = None
    preprocessing: Preprocessing | None = None
    output: str = "either"
    fixed: bool = False
    declared: bool = True

    def __post_init__(self):
        if self.input is not None and self.input not in INPUT_KINDS:
            raise InputError(f"trained input must be one of {INPUT_KINDS} or None, got {self.input!r}")
        if self.output not in OUTPUT_KINDS:
            raise InputError(f"model output must be one of {OUTPUT_KINDS}, got {self.output!r}")

    @property
    def end_to_end(self) -> bool:
        return self.output == "spectra"

    def to_dict(self) -> dict[str, Any]:
        return {"input": self.input,
                "preprocessing": None if self.preprocessing is None else self.preprocessing.to_dict(),
                "output": self.output, "fixed": self.fixed, "declared": self.declared}

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> "TrainedFor":
        if not isinstance(d, dict):
            raise InputError(f"not a trained-input declaration: {d!r}")
        try:
            pp = Preprocessing.from_dict(d.get("preprocessing"))
        except ValueError as exc:
            raise InputError(str(exc)) from None
        return cls(input=d.get("input"), preprocessing=pp, output=d.get("output", "either"),
                   fixed=bool(d.get("fixed", False)), declared=bool(d.get("declared", True)))

    def label(self) -> str:
        """e.g. ``HDR, reinhard key 0.18, ◇`` for tables and notes."""
        parts = ["fixed" if self.fixed else (self.input.upper() if self.input else "any input")]
        parts.append(self.preprocessing.label() if self.preprocessing else "no pre-processing")
        parts.append({"shape": "◇ (luminance restored)", "spectra": "e2e (not restored)",
                      "either": "restoration optional"}[self.output])
        return ", ".join(parts)


#: Declaration of a model that says nothing (user functions): scored everywhere asked.
UNDECLARED = TrainedFor(declared=False)


def trained_for(model: Any) -> TrainedFor:
    """The :class:`TrainedFor` of ``model``, from its attributes.

    ``model.trained_for`` wins. Older self-contained models (ONNX graphs,
    networks) carry ``preprocessing`` (``"reinhard"``/``None``) and
    ``restores_luminance`` instead: a ``"reinhard"`` there is the paper's fixed
    scale 1, a restoring model outputs a shape, one that does not is end to end.
    """
    tf = getattr(model, "trained_for", None)
    if isinstance(tf, TrainedFor):
        return tf
    if isinstance(tf, dict):
        return TrainedFor.from_dict(tf)
    if hasattr(model, "preprocessing"):
        pp = PAPER_PREPROCESSING if getattr(model, "preprocessing") else None
        out = "shape" if getattr(model, "restores_luminance", False) else "spectra"
        return TrainedFor(input=None, preprocessing=pp, output=out)
    return UNDECLARED


def applies_preprocessing(model: Any) -> bool:
    """True if ``model`` applies its declared pre-processing itself (networks, ONNX graphs)."""
    if hasattr(model, "applies_preprocessing"):
        return bool(model.applies_preprocessing)
    return hasattr(model, "preprocessing")  # older self-contained models


@runtime_checkable
class SSRModelProtocol(Protocol):
    name: str
    wavelengths: np.ndarray

    def __call__(self, rgb: np.ndarray) -> np.ndarray: ...


class SSRModel:
    """Base class of SSR models: subclasses implement :meth:`predict`.

    ``__call__`` checks the input ``(H, W, 3)``, casts it to float32, calls
    :meth:`predict` and checks the output ``(H, W, B)`` is finite.
    """

    name: str = "model"
    wavelengths: np.ndarray = WAVELENGTHS_31
    description: str = ""

    def predict(self, rgb: np.ndarray) -> np.ndarray:  # pragma: no cover - abstract
        raise NotImplementedError

    def __call__(self, rgb: np.ndarray) -> np.ndarray:
        rgb = check_rgb(rgb, self.name)
        out = np.asarray(self.predict(rgb))
        return check_output(out, rgb.shape, self.wavelengths, self.name)

    def __repr__(self) -> str:
        wl = np.asarray(self.wavelengths)
        return f"{type(self).__name__}(name={self.name!r}, bands={wl.size} {wl[0]:g}..{wl[-1]:g} nm)"


def check_rgb(rgb: np.ndarray, name: str = "model") -> np.ndarray:
    """Return ``rgb`` as a float32 ``(H, W, 3)`` array or raise :class:`InputError`."""
    rgb = np.asarray(rgb)
    if rgb.ndim != 3 or rgb.shape[-1] != 3:
        raise InputError(f"{name}: input must be (H, W, 3) RGB, got shape {rgb.shape}")
    return rgb.astype(np.float32, copy=False)


def all_finite(a: np.ndarray) -> bool:
    """True if no element of ``a`` is NaN or ±inf, without a full-size boolean temporary.

    A float64 sum is non-finite exactly when some element is (finite float32/64
    values cannot overflow it: 3.4e38 · 1e9 ≪ 1.8e308 for float32; float64
    input falls back to ``isfinite`` when the sum overflows).
    """
    a = np.asarray(a)
    if a.dtype.kind not in "fc":
        return True
    with np.errstate(over="ignore", invalid="ignore"):
        if np.isfinite(a.sum(dtype=np.float64)):
            return True
    return bool(np.isfinite(a).all())


def check_output(out: np.ndarray, in_shape: tuple, wavelengths: np.ndarray,
                 name: str = "model") -> np.ndarray:
    """Check a model output against the contract; return it as float32."""
    nb = np.asarray(wavelengths).size
    want = (*in_shape[:2], nb)
    if tuple(out.shape) != want:
        raise InputError(f"{name}: output shape {tuple(out.shape)} breaks the contract, "
                         f"expected {want} (H, W, bands)")
    out = out.astype(np.float32, copy=False)
    if not all_finite(out):
        n = int(np.count_nonzero(~np.isfinite(out)))
        raise InputError(f"{name}: output has {n} NaN/inf values")
    return out


#: Attributes of a wrapped callable that say what it was trained for and how it must be
#: called (see the module notes); :class:`FunctionModel` carries them over.
_DECLARATIONS = ("trained_for", "applies_preprocessing", "preprocessing", "restores_luminance",
                 "standard_spectrum")


class FunctionModel(SSRModel):
    """Wrap a plain function ``rgb (H, W, 3) → spectra (H, W, B)`` as a model."""

    def __init__(self, fn: Callable[[np.ndarray], np.ndarray], *, name: str,
                 wavelengths: np.ndarray | None = None, description: str = ""):
        self.fn = fn
        self.name = name
        wl = getattr(fn, "wavelengths", None) if wavelengths is None else wavelengths
        self.wavelengths = np.asarray(WAVELENGTHS_31 if wl is None else wl, dtype=np.float64)
        self.description = description or (inspect.getdoc(fn) or "").split("\n")[0]
        # What the wrapped object declares about itself must survive the wrapping: a user
        # function carrying ``trained_for`` (HDR, no pre-processing, end to end) was
        # otherwise scored as undeclared, under every setting, restored and tone-mapped.
        for attr in _DECLARATIONS:
            if hasattr(fn, attr):
                setattr(self, attr, getattr(fn, attr))

    def predict(self, rgb: np.ndarray) -> np.ndarray:
        return self.fn(rgb)


