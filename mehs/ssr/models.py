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
  ``(N, H, W, 3)`` NHWC; the output must be ``(N, B, H, W)`` or ``(N, H, W, B)``.
  Bands: the ``wavelengths=`` keyword, else a metadata property
  ``wavelengths`` (comma-separated nm), else 400:700:10 when B = 31;
- a fitted regression baseline file (``.npz``, from ``mehs train-baseline``);
- a torch checkpoint (``.pt``/``.pth``) via :func:`mehs.ssr.net.export.load_torch_model`
  (torch extra), which dispatches on the checkpoint's ``arch`` through the registry;
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
from mehs.rgb import WAVELENGTHS_31
from mehs.ssr.contract import (FunctionModel, SSRModel, SSRModelProtocol, all_finite,  # noqa: F401
                               check_output, check_rgb)
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
        return OnnxModel(text, **kwargs)
    if low.endswith(".pt") or low.endswith(".pth"):
        try:
            from mehs.ssr.net.export import load_torch_model
        except ImportError as exc:
            raise InputError(f"a torch checkpoint needs the torch extra: pip install "
                             f"'mehs[torch]' ({exc})", text) from None
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


def onnx_session_options():
    """onnxruntime session options for SSR models: no memory patterns.

    A memory pattern is a block that onnxruntime plans, allocates and keeps for each
    input shape it has seen. Tiles come in several shapes, and the kept blocks add up:
    the small hdrssr network on 2048×1024 in 640×1024 tiles peaked at 3.11 GB with
    patterns and 1.84 GB without (8.9 s against 11.6 s), and three whole-image runs at
    9.19 GB against 5.48 GB; the first whole run was faster without (7.6 s against
    12.5 s), only the third, same-shape run slower (7.5 s against 4.9 s). Memory that
    depends on the shapes seen before cannot be planned (:mod:`mehs.ssr.tiling`).
    Pass ``session_options=`` to :class:`OnnxModel` to choose otherwise.
    """
    import onnxruntime as ort

    so = ort.SessionOptions()
    so.enable_mem_pattern = False
    return so


class OnnxModel(SSRModel):
    """An ONNX SSR model run with onnxruntime on the CPU (see module notes for layouts)."""

    def __init__(self, path: str | Path, *, name: str | None = None,
                 wavelengths: np.ndarray | None = None, providers: list[str] | None = None,
                 session_options=None):
        path = Path(path)
        if not path.is_file():
            raise InputError("no such ONNX model file", path)
        try:
            import onnxruntime as ort
        except ImportError:
            raise InputError("onnxruntime is not installed: pip install 'mehs[onnx]'",
                             path) from None
        if session_options is None:
            session_options = onnx_session_options()
        try:
            self.session = ort.InferenceSession(
                str(path), sess_options=session_options,
                providers=providers or ["CPUExecutionProvider"])
        except Exception as exc:  # onnxruntime raises its own exception types
            raise FormatError(f"onnxruntime cannot load the model ({exc})", path) from None
        self.path = path
        self.name = name or path.stem
        # what a graph rebuilt for image-wide tiling means (mehs.ssr.tiling_onnx) also
        # needs: its extra inputs' values for a plain run, and the one output wanted
        self._run_feeds: dict = {}
        self._run_outputs: list[str] | None = None
        inputs = self.session.get_inputs()
        if len(inputs) != 1:
            raise FormatError(f"the model has {len(inputs)} inputs; SSR models take one", path)
        self.input_name = inputs[0].name
        shape = list(inputs[0].shape)
        if len(shape) != 4:
            raise FormatError(f"input shape {shape} is not 4-D (NCHW or NHWC)", path)
        if shape[1] == 3 and shape[3] != 3:
            self.layout = "NCHW"
        elif shape[3] == 3:
            self.layout = "NHWC"
        else:
            raise FormatError(f"cannot tell NCHW from NHWC in input shape {shape}", path)
        self.input_type = inputs[0].type
        meta = self.session.get_modelmeta().custom_metadata_map or {}
        # A self-contained graph (e.g. exported by `mehs train-ssr`) says whether it
        # applies Reinhard and restores luminance itself, so the pipeline does
        # neither a second time.
        if "mehs_preprocessing" in meta:
            pp = meta["mehs_preprocessing"].strip().lower()
            self.preprocessing = None if pp in ("", "none", "off", "false") else pp
        if "mehs_luminance_restored" in meta:
            self.restores_luminance = meta["mehs_luminance_restored"].strip().lower() in (
                "1", "true", "yes", "on")
        if "mehs_trained_for" in meta:
            from mehs.ssr.contract import TrainedFor

            try:
                self.trained_for = TrainedFor.from_dict(json.loads(meta["mehs_trained_for"]))
            except (ValueError, InputError) as exc:
                raise FormatError(f"metadata 'mehs_trained_for' is damaged ({exc})", path) from None
        if wavelengths is None:
            if "wavelengths" in meta:
                try:
                    wavelengths = [float(v) for v in meta["wavelengths"].replace(";", ",").split(",")]
                except ValueError:
                    raise FormatError("metadata 'wavelengths' is not a list of numbers", path) from None
        self._declared = None if wavelengths is None else np.asarray(wavelengths, dtype=np.float64)
        self.wavelengths = WAVELENGTHS_31 if self._declared is None else self._declared
        self.description = f"ONNX model {path.name} ({self.layout})"

    def predict(self, rgb: np.ndarray) -> np.ndarray:
        from mehs.ssr.tiling import tiled_onnx_call

        return tiled_onnx_call(self, self._predict_whole, rgb)  # tiles when memory is short

    def _predict_whole(self, rgb: np.ndarray) -> np.ndarray:
        y = self.session.run(self._run_outputs, {self.input_name: self._graph_input(rgb),
                                                 **self._run_feeds})[0]
        return self._spectra(y, rgb.shape[:2])

    def release_memory(self) -> None:
        """Return the memory onnxruntime's arena keeps from earlier runs to the system.

        The arena keeps the peak of the largest run so far; the tiling budget is what
        the process does not hold (:func:`mehs.ssr.tiling.default_budget`), so after a
        large whole-image run a tiled call would find almost none. A tiny run with the
        arena-shrinkage option frees every arena region not in use.
        """
        import onnxruntime as ort

        ro = ort.RunOptions()
        ro.add_run_config_entry("memory.enable_memory_arena_shrinkage", "cpu:0")
        x = np.zeros((32, 32, 3), dtype=np.float32)
        try:
            self.session.run(self._run_outputs, {self.input_name: self._graph_input(x),
                                                 **self._run_feeds}, ro)
        except Exception:  # noqa: BLE001 - a graph that refuses 32×32: nothing released
            pass
        from mehs.ssr.allocator import trim_heap

        trim_heap()     # arena regions below the mmap threshold were freed to the C heap

    def _graph_input(self, rgb: np.ndarray) -> np.ndarray:
        """``(H, W, 3)`` → the graph's input tensor (its layout and float type)."""
        x = rgb[None]
        if self.layout == "NCHW":
            x = x.transpose(0, 3, 1, 2)
        dtype = np.float16 if "float16" in self.input_type else np.float32
        return np.ascontiguousarray(x, dtype=dtype)

    def _spectra(self, y, shape: tuple[int, int]) -> np.ndarray:
        """The graph's output for an ``H × W`` input → float32 ``(H, W, B)``."""
        y = np.asarray(y)
        h, w = shape
        if y.ndim != 4 or y.shape[0] != 1:
            raise InputError(f"{self.name}: output shape {y.shape} is not (1, B, H, W) or (1, H, W, B)")
        if y.shape[2:] == (h, w) and (y.shape[1:3] != (h, w) or self.layout == "NCHW"):
            y = y[0].transpose(1, 2, 0)
        elif y.shape[1:3] == (h, w):
            y = y[0]
        else:
            raise InputError(f"{self.name}: output shape {y.shape} does not match input {h}×{w}")
        if self._declared is None and y.shape[-1] != 31:
            raise InputError(f"{self.name}: the model gives {y.shape[-1]} bands; declare them "
                             "with wavelengths= or a 'wavelengths' metadata property", self.path)
        return y.astype(np.float32, copy=False)
