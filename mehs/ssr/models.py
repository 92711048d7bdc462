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
  ``(N, H, W, 3)`` NHWC; the (first) output must be ``(N, B, H, W)`` or
  ``(N, H, W, B)``, its band axis read from the declared output shape (an ambiguous
  one is refused). Fixed spatial axes: that size only, run whole. Bands: the
  ``wavelengths=`` keyword, else a metadata property ``wavelengths``
  (comma-separated nm), else the sidecar, else 400:700:10 when B = 31;
- sidecar ``<file>.json`` next to a ``.onnx`` or TorchScript file (:func:`read_sidecar`):
  its ``trained_for`` and ``wavelengths``, what a foreign graph cannot say itself;
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

from mehs.errors import FormatError, InputError, first_line
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


#: onnxruntime input types an SSR graph may take → the numpy type fed to it.
_FLOAT_TYPES = {"tensor(float)": np.float32, "tensor(float16)": np.float16,
                "tensor(double)": np.float64}
_FLOAT16_MAX = float(np.finfo(np.float16).max)


def _output_layout(shape, fixed_size: tuple) -> str | None:
    """``"NCHW"``/``"NHWC"`` when a graph's declared output ``shape`` tells it, else ``None``.

    A band axis of fixed size next to two dynamic spatial axes tells it (``[N, 31, H, W]``);
    with every axis fixed, the one matching the input's fixed size does.
    """
    if not isinstance(shape, (list, tuple)) or len(shape) != 4:
        return None
    fixed = [isinstance(d, int) and d > 0 for d in shape]
    nchw = fixed[1] and not (fixed[2] or fixed[3])
    nhwc = fixed[3] and not (fixed[1] or fixed[2])
    if nchw != nhwc:
        return "NCHW" if nchw else "NHWC"
    if all(fixed) and None not in fixed_size:
        hw = tuple(fixed_size)
        fits = [lay for lay, s in (("NCHW", tuple(shape[2:])), ("NHWC", tuple(shape[1:3])))
                if s == hw]
        return fits[0] if len(fits) == 1 else None
    return None


SIDECAR_SUFFIX = ".json"
_SIDECAR_KEYS = {"trained_for", "wavelengths"}


def read_sidecar(model_path: str | Path) -> dict[str, Any]:
    """The declaration next to a foreign model file: ``<file>.json`` (e.g. ``mst.onnx.json``).

    ``{"trained_for": {...TrainedFor.to_dict()...}, "wavelengths": [400, 410, ...]}``, both
    optional: what a graph from elsewhere cannot say itself. ``{}`` when there is none.
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
    return out


def _with_sidecar(path: str, make: Callable[..., Any], kwargs: dict[str, Any]) -> Any:
    """``make(path, **kwargs)`` with what its sidecar declares: the wavelengths (unless given)
    and ``trained_for``."""
    side = read_sidecar(path)
    if "wavelengths" in side and kwargs.get("wavelengths") is None:
        kwargs = {**kwargs, "wavelengths": side["wavelengths"]}
    return _declare(make(path, **kwargs), side)


def _declare(model: Any, side: dict[str, Any]) -> Any:
    """``model`` with the sidecar's ``trained_for``; refused where the graph declares its own."""
    tf = side.get("trained_for")
    if tf is None:
        return model
    if getattr(model, "trained_for", None) is not None or hasattr(model, "preprocessing"):
        raise FormatError("model declaration: the model declares what it was trained for "
                          "itself (mehs metadata); remove 'trained_for' here", side["path"])
    model.trained_for = tf
    return model


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
        if self.input_type not in _FLOAT_TYPES:
            raise FormatError(f"input type {self.input_type} is not a float tensor; SSR models "
                              "take linear float RGB (float, float16 or double)", path)
        if isinstance(shape[0], int) and shape[0] != 1:
            raise FormatError(f"the graph's batch axis is fixed to {shape[0]} (input shape "
                              f"{shape}); images are run one at a time: export it with batch 1 "
                              "or a dynamic batch axis", path)
        self.input_shape = shape
        # Spatial axes the graph fixes (ints in its input shape, e.g. exported at 482×512
        # without dynamic axes): onnxruntime refuses any other size, tiles included.
        hw = shape[2:] if self.layout == "NCHW" else shape[1:3]
        self.fixed_size = tuple(d if isinstance(d, int) and d > 0 else None for d in hw)
        outputs = self.session.get_outputs()
        self.output_layout = _output_layout(outputs[0].shape, self.fixed_size)
        # the spectra are the first output (torch.onnx.export writes a returned tuple in
        # order, the main output first); errors name the others
        self._which = ("" if len(outputs) == 1 else
                       f" (the first of its {len(outputs)} outputs "
                       f"{', '.join(o.name for o in outputs)}, is taken for the spectra)")
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

        if any(d is not None for d in self.fixed_size):
            # a graph of fixed size runs whole: tiles (and the tiler's 256×256 memory
            # probe) have other sizes, which it refuses
            self._check_size(rgb.shape[:2])
            return self._predict_whole(rgb)
        return tiled_onnx_call(self, self._predict_whole, rgb)  # tiles when memory is short

    def _check_size(self, hw: tuple[int, int]) -> None:
        """Refuse, naming both sizes, an image the graph's fixed spatial axes do not take."""
        if all(f is None or f == n for f, n in zip(self.fixed_size, hw)):
            return
        want = "×".join("any" if f is None else str(f) for f in self.fixed_size)
        raise InputError(f"{self.name}: the graph takes {want} images only (its input shape is "
                         f"{self.input_shape}), this one is {hw[0]}×{hw[1]}: export it with "
                         "dynamic height and width axes, or crop the images to that size "
                         "(public datasets: --hs-crop HxW)", self.path)

    def _predict_whole(self, rgb: np.ndarray) -> np.ndarray:
        self._check_size(rgb.shape[:2])
        try:
            y = self.session.run(self._run_outputs, {self.input_name: self._graph_input(rgb),
                                                     **self._run_feeds})[0]
        except Exception as exc:  # onnxruntime's own types, none of them a builtin error
            msg = str(exc)
            if isinstance(exc, InputError) or "alloc" in msg.lower() or "memory" in msg.lower():
                raise  # ours, or out of memory: the tiler and the timing read those
            h, w = rgb.shape[:2]
            raise InputError(f"{self.name}: onnxruntime cannot run the graph on a {h}×{w} "
                             f"image ({first_line(msg)}); a graph that needs sizes divisible "
                             "by 8, 16 or 32 must pad inside itself (as MST++'s does)",
                             self.path) from None
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
        dtype = _FLOAT_TYPES[self.input_type]
        if dtype == np.float16 and x.size:
            # HDR radiance overflows float16 (max 65504) to inf: say so, rather than
            # report the inf the graph then returns as the model's fault
            peak = float(np.abs(x).max())
            if not peak <= _FLOAT16_MAX:
                raise InputError(f"{self.name}: the graph takes float16 input, whose range "
                                 f"ends at {_FLOAT16_MAX:g}; this image reaches {peak:.4g} "
                                 "(scale the data, e.g. --hs-scale, or export in float32)",
                                 self.path)
        return np.ascontiguousarray(x, dtype=dtype)

    def _spectra(self, y, shape: tuple[int, int]) -> np.ndarray:
        """The graph's output for an ``H × W`` input → float32 ``(H, W, B)``."""
        y = np.asarray(y)
        h, w = shape
        if y.ndim != 4 or y.shape[0] != 1:
            raise InputError(f"{self.name}: output shape {y.shape} is not (1, B, H, W) or "
                             f"(1, H, W, B){self._which}", self.path)
        fits = [lay for lay, hw in (("NCHW", y.shape[2:]), ("NHWC", y.shape[1:3])) if hw == (h, w)]
        if self.output_layout is not None:
            # the graph's declared output shape says where the bands are
            fits = [lay for lay in fits if lay == self.output_layout]
        if not fits:
            raise InputError(f"{self.name}: output shape {y.shape} does not match the {h}×{w} "
                             "input (a graph that crops or pads its output must undo it "
                             f"itself){self._which}", self.path)
        if len(fits) == 2:
            # (1, 31, 31, 31) on a 31×31 image: either reading fits, and the input's
            # layout says nothing about the output's
            raise InputError(f"{self.name}: output shape {y.shape} on a {h}×{w} image is "
                             "ambiguous and the graph's output shape does not tell where the "
                             "bands are (give its band axis a fixed size)", self.path)
        y = y[0].transpose(1, 2, 0) if fits[0] == "NCHW" else y[0]
        if self._declared is not None and y.shape[-1] != self._declared.size:
            raise InputError(f"{self.name}: the model gives {y.shape[-1]} bands{self._which}, "
                             f"but {self._declared.size} wavelengths are declared for it",
                             self.path)
        if self._declared is None and y.shape[-1] != 31:
            raise InputError(f"{self.name}: the model gives {y.shape[-1]} bands{self._which}; "
                             "declare them with wavelengths=, a 'wavelengths' metadata property "
                             f"or {self.path.name}{SIDECAR_SUFFIX}", self.path)
        return y.astype(np.float32, copy=False)
