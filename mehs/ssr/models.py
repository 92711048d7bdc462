"""Load SSR models by name, file or ``module:function``: :func:`load_model`.

The contract (:class:`SSRModel`, :class:`TrainedFor`) lives in
:mod:`mehs.ssr.contract`, the registry in :mod:`mehs.ssr.registry`; both are
re-exported here. This module sits *above* the baselines and networks (it
imports them to fill the registry), never below.

Ways to name a model (``load_model(spec, **kwargs)``)
-----------------------------------------------------
- a registered name: ``smits``, ``mallett``, ``regression`` (needs ``path=`` to a
  fitted model, see :mod:`mehs.ssr.baselines`), plus anything registered with
  :func:`register_model` (every registered network architecture is a model
  name too, via :mod:`mehs.ssr.net.register`, when torch imports);
- ``package.module:function`` or ``path/to/file.py:function``. The object found is
  used as follows: an object with a ``wavelengths`` attribute that is callable
  is a model already; a class, or a callable that needs no positional argument,
  is a *factory* called with ``**kwargs`` and must return a model (or a plain
  function); any other callable is a function ``rgb → spectra``. **Output band
  set:** the ``wavelengths`` attribute of the object (or the ``wavelengths=``
  keyword), default 400:700:10 (:data:`mehs.rgb.WAVELENGTHS_31`);
- a ``.onnx`` file, run with onnxruntime (optional extra ``mehs[onnx]``). The
  layout is read from the model's input shape: ``(N, 3, H, W)`` is NCHW,
  ``(N, H, W, 3)`` NHWC; the spectra output must be ``(N, B, H, W)`` or
  ``(N, H, W, B)``, its band axis read from the declared output shape (an ambiguous
  one is refused). Fixed spatial axes: that size only, run whole. Bands: the
  ``wavelengths=`` keyword, else a metadata property ``wavelengths``
  (comma-separated nm), else the sidecar, else 400:700:10 when B = 31. A graph with several
  outputs: the ``output=`` keyword or the sidecar's ``output`` names the spectra; unnamed,
  the one output whose declared shape can hold the band cube is taken, and a graph with
  several such is refused (the error lists them);
- sidecar ``<file>.json`` next to a ``.onnx`` or TorchScript file (:func:`read_sidecar`):
  its ``trained_for``, ``wavelengths`` and (ONNX) ``output``, what a foreign graph cannot
  say itself;
- a fitted regression baseline file (``.npz``, from ``mehs train-baseline``);
- a torch checkpoint (``.pt``/``.pth``) via :func:`mehs.ssr.net.export.load_torch_model`
  (torch extra), which dispatches on the checkpoint's ``arch`` through the registry, or
  a TorchScript archive (:class:`mehs.ssr.net.export.TorchScriptModel`);
- ``name=SPEC`` (any of the above): the same model, shown as ``name`` in tables.
"""

from __future__ import annotations

import importlib
import json
import importlib.util
import inspect
from pathlib import Path
from typing import Any, Callable

import numpy as np

from mehs.errors import FormatError, InputError
from mehs.ssr.contract import (FunctionModel, SSRModel, SSRModelProtocol, all_finite,  # noqa: F401
                               check_output, check_rgb)
from mehs.ssr.onnx_model import (SIDECAR_SUFFIX, OnnxModel, _output_layout,  # noqa: F401
                                 onnx_session_options)
from mehs.ssr.registry import MODELS, ModelEntry, load_providers, register_model  # noqa: F401

#: Re-exported from the contract and the registry, where they live.
__all__ = ["MODELS", "FunctionModel", "ModelEntry", "OnnxModel", "SSRModel", "SSRModelProtocol",
           "all_finite", "check_output", "check_rgb", "list_models", "load_model",
           "register_model", "split_named_spec"]


def _load_builtins() -> None:
    import mehs.ssr.baselines  # noqa: F401  (registers the built-ins)


def _load_plugins() -> None:
    """Import every registering module once (torch networks quietly skipped without torch)."""
    load_providers()


def list_models() -> dict[str, str]:
    """Registered model names → one-line descriptions."""
    _load_plugins()
    return {k: v.description for k, v in sorted(MODELS.items())}


def _as_model(obj: Any, name: str, wavelengths=None) -> Any:
    if callable(obj) and hasattr(obj, "wavelengths") and hasattr(obj, "name") and wavelengths is None:
        return obj
    if callable(obj):
        return FunctionModel(obj, name=getattr(obj, "name", None) or name,
                             wavelengths=wavelengths)
    raise InputError(f"{name}: the factory returned {type(obj).__name__}, not a model")


def _import_object(spec: str) -> Any:
    mod_name, _, attr = spec.rpartition(":")
    if not mod_name or not attr:
        raise InputError(f"model {spec!r}: expected 'package.module:function'")
    try:
        if mod_name.endswith(".py"):
            path = Path(mod_name)
            if not path.is_file():
                raise InputError("no such Python file", path)
            mspec = importlib.util.spec_from_file_location(f"_mehs_user_{path.stem}", path)
            module = importlib.util.module_from_spec(mspec)
            try:
                mspec.loader.exec_module(module)  # type: ignore[union-attr]
            except ImportError:
                raise
            except Exception as exc:  # noqa: BLE001 - the user's file failed: say which
                raise InputError(f"model {spec!r}: running {path} failed "
                                 f"({type(exc).__name__}: {exc})", path) from None
        else:
            module = importlib.import_module(mod_name)
    except ImportError as exc:
        raise InputError(f"model {spec!r}: cannot import {mod_name!r} ({exc})") from None
    obj = module
    for part in attr.split("."):
        try:
            obj = getattr(obj, part)
        except AttributeError:
            raise InputError(f"model {spec!r}: {mod_name!r} has no attribute {attr!r}") from None
    return obj


def split_named_spec(spec: str) -> tuple[str | None, str]:
    """``"ours=runs/a/best.pt"`` → ``("ours", "runs/a/best.pt")``; no label → ``(None, spec)``.

    The label is what precedes the first ``=`` when it is a plain name (letters,
    digits, ``_ - .``, no path separator), so ``dir=x/best.pt`` names a row but a
    path containing ``=`` further on is left alone.
    """
    head, sep, tail = spec.partition("=")
    head = head.strip()
    if sep and head and tail.strip() and all(c.isalnum() or c in "_-.+" for c in head):
        return head, tail.strip()
    return None, spec


def _needs_positional(fn: Callable) -> bool:
    try:
        sig = inspect.signature(fn)
    except (TypeError, ValueError):
        return True
    return any(p.default is p.empty and p.kind in (p.POSITIONAL_ONLY, p.POSITIONAL_OR_KEYWORD)
               for p in sig.parameters.values())


def load_model(spec: Any, **kwargs: Any) -> Any:
    """Return a model for ``spec`` (see the module notes for the accepted forms).

    ``spec`` may also be a model object already (returned unchanged) or a plain
    callable (wrapped). ``kwargs`` go to the factory; ``wavelengths=`` declares
    the output bands of plain functions and ONNX models.
    """
    if not isinstance(spec, (str, Path)):
        if callable(spec):
            return _as_model(spec, getattr(spec, "__name__", "model"), kwargs.get("wavelengths"))
        raise InputError(f"cannot make a model from {type(spec).__name__}")
    text = str(spec).strip()
    label, text = split_named_spec(text)
    if label is not None:
        model = load_model(text, **kwargs)
        try:
            model.name = label
        except AttributeError:  # a model with a read-only name: wrap it
            model = FunctionModel(model, name=label, wavelengths=model.wavelengths)
        return model
    low = text.lower()
    if low.endswith(".onnx"):
        return _with_sidecar(text, OnnxModel, kwargs)
    if low.endswith(".pt") or low.endswith(".pth"):
        try:
            from mehs.ssr.net.export import is_torchscript, load_torch_model
        except ImportError as exc:
            raise InputError(f"a torch checkpoint needs the torch extra: pip install "
                             f"'mehs[torch]' ({exc})", text) from None
        if Path(text).is_file() and is_torchscript(text):
            return _with_sidecar(text, load_torch_model, kwargs)
        return load_torch_model(text, **kwargs)
    if low.endswith(".npz") or low.endswith(".json"):
        from mehs.ssr.baselines import RegressionModel

        return RegressionModel.load(text)
    if ":" in text and not (len(text) > 1 and text[1] == ":" and "\\" in text):
        obj = _import_object(text)
        name = kwargs.pop("name", None) or text.rpartition(":")[2]
        wl = kwargs.pop("wavelengths", None)
        if callable(obj) and hasattr(obj, "wavelengths") and not inspect.isclass(obj):
            return _as_model(obj, name, wl)
        if inspect.isclass(obj) or (callable(obj) and not _needs_positional(obj)):
            return _as_model(obj(**kwargs), name, wl)
        if callable(obj):
            return FunctionModel(obj, name=name, wavelengths=wl)
        raise InputError(f"model {text!r} is a {type(obj).__name__}, not callable")
    _load_builtins()
    entry = MODELS.get(low)
    if entry is None:
        _load_plugins()
        entry = MODELS.get(low)
    if entry is None:
        raise InputError(f"unknown model {text!r}; known: {', '.join(sorted(MODELS))} "
                         "(or give package.module:function, a .onnx or a .npz file)")
    return _as_model(entry.factory(**kwargs), entry.name)


_SIDECAR_KEYS = {"trained_for", "wavelengths", "output", "size_multiple"}


def read_sidecar(model_path: str | Path) -> dict[str, Any]:
    """The declaration next to a foreign model file: ``<file>.json`` (e.g. ``mst.onnx.json``).

    ``{"trained_for": {...TrainedFor.to_dict()...}, "wavelengths": [400, 410, ...],
    "output": "spectra", "size_multiple": 8}``, all optional: what a graph from elsewhere
    cannot say itself (``output``: which of an ONNX graph's outputs holds the spectra;
    ``size_multiple``: the graph takes only heights and widths divisible by it, see
    :mod:`mehs.ssr.tiling_pad`). ``{}`` when there is none.
    """
    path = Path(str(model_path) + SIDECAR_SUFFIX)
    if not path.is_file():
        return {}
    try:
        d = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, ValueError) as exc:
        raise FormatError(f"model declaration is not readable JSON ({exc})", path) from None
    if not isinstance(d, dict) or set(d) - _SIDECAR_KEYS:
        keys = sorted(set(d) - _SIDECAR_KEYS) if isinstance(d, dict) else type(d).__name__
        raise FormatError(f"model declaration: expected an object with keys "
                          f"{sorted(_SIDECAR_KEYS)}, got {keys}", path)
    out: dict[str, Any] = {"path": path}
    if d.get("trained_for") is not None:
        from mehs.ssr.contract import TrainedFor

        try:
            out["trained_for"] = TrainedFor.from_dict(d["trained_for"])
        except InputError as exc:
            raise FormatError(f"model declaration: 'trained_for' {exc.problem}", path) from None
    if d.get("wavelengths") is not None:
        try:
            wl = np.asarray(d["wavelengths"], dtype=np.float64).reshape(-1)
        except (TypeError, ValueError):
            wl = np.array([np.nan])
        if not wl.size or not np.all(np.isfinite(wl)):
            raise FormatError("model declaration: 'wavelengths' is not a list of numbers (nm)",
                              path)
        out["wavelengths"] = wl
    if d.get("output") is not None:
        if not isinstance(d["output"], str) or not d["output"]:
            raise FormatError(f"model declaration: 'output' must be the name of the graph's "
                              f"output that holds the spectra, got {d['output']!r}", path)
        out["output"] = d["output"]
    if d.get("size_multiple") is not None:
        from mehs.ssr.tiling_pad import check_multiple

        try:
            out["size_multiple"] = check_multiple(d["size_multiple"], "'size_multiple'")
        except InputError as exc:
            raise FormatError(f"model declaration: {exc.problem}", path) from None
    return out


def _with_sidecar(path: str, make: Callable[..., Any], kwargs: dict[str, Any]) -> Any:
    """``make(path, **kwargs)`` with what its sidecar declares: the wavelengths and the ONNX
    output (unless given) and ``trained_for``."""
    side = read_sidecar(path)
    if "wavelengths" in side and kwargs.get("wavelengths") is None:
        kwargs = {**kwargs, "wavelengths": side["wavelengths"]}
    if "output" in side:
        if make is not OnnxModel:
            raise FormatError("model declaration: 'output' names one of an ONNX graph's "
                              "outputs; this model is not an ONNX graph", side["path"])
        if kwargs.get("output") is None:
            kwargs = {**kwargs, "output": side["output"]}
    return _declare(make(path, **kwargs), side)


def _declare(model: Any, side: dict[str, Any]) -> Any:
    """``model`` with the sidecar's ``trained_for`` and ``size_multiple``; refused where the
    graph declares its own (a different multiple, or any ``trained_for``)."""
    k = side.get("size_multiple")
    if k is not None:
        own = getattr(model, "size_multiple", 1) or 1
        if own not in (1, k):
            raise FormatError(f"model declaration: 'size_multiple' {k} contradicts the "
                              f"model's own {own} (mehs metadata); remove it here", side["path"])
        model.size_multiple = k
    tf = side.get("trained_for")
    if tf is None:
        return model
    if getattr(model, "trained_for", None) is not None or hasattr(model, "preprocessing"):
        raise FormatError("model declaration: the model declares what it was trained for "
                          "itself (mehs metadata); remove 'trained_for' here", side["path"])
    model.trained_for = tf
    return model
