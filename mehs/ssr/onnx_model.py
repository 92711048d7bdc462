"""ONNX SSR models run with onnxruntime: :class:`OnnxModel` (loaded through
:func:`mehs.ssr.models.load_model`, which reads the ``<file>.json`` sidecar).

Split from :mod:`mehs.ssr.models`, which re-exports everything here.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from mehs.errors import FormatError, InputError, first_line
from mehs.rgb import WAVELENGTHS_31
from mehs.ssr.contract import SSRModel

#: The declaration next to a foreign model file: ``<file>.json`` (:func:`mehs.ssr.models.read_sidecar`).
SIDECAR_SUFFIX = ".json"

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


def _could_be_cube(shape, bands: int, fixed_size: tuple) -> bool:
    """Whether a graph output's declared ``shape`` can be ``(1, B, H, W)`` or ``(1, H, W, B)``
    for ``bands`` = B on the graph's spatial size (unknown axes can be anything)."""
    if shape is None:
        return True                       # no shape information: it could
    if not isinstance(shape, (list, tuple)) or len(shape) != 4:
        return False

    def can(d, want) -> bool:
        return not (isinstance(d, int) and d > 0) or want is None or d == want

    h, w = fixed_size
    layout = _output_layout(shape, fixed_size)
    if layout is not None:    # a fixed axis among dynamic ones is the band axis: (N, 1, H, W)
        return can(shape[0], 1) and shape[1 if layout == "NCHW" else 3] == bands
    return can(shape[0], 1) and (
        (can(shape[1], bands) and can(shape[2], h) and can(shape[3], w))
        or (can(shape[1], h) and can(shape[2], w) and can(shape[3], bands)))


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
    """An ONNX SSR model run with onnxruntime on the CPU (see module notes for layouts).

    ``size_multiple``: the graph takes only heights and widths divisible by it (a
    down-sampling network that does not pad itself); default: the graph's metadata
    property ``mehs_size_multiple`` (written by :func:`mehs.ssr.net.export.export_onnx`),
    else 1. Every run is then reflect-padded to the multiple and cropped back
    (:mod:`mehs.ssr.tiling_pad`), tiles included.
    """

    def __init__(self, path: str | Path, *, name: str | None = None,
                 wavelengths: np.ndarray | None = None, providers: list[str] | None = None,
                 session_options=None, output: str | None = None,
                 size_multiple: int | None = None):
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
        from mehs.ssr.tiling_pad import ONNX_SIZE_MULTIPLE_KEY, check_multiple

        if size_multiple is None and meta.get(ONNX_SIZE_MULTIPLE_KEY, "").strip():
            try:
                size_multiple = check_multiple(meta[ONNX_SIZE_MULTIPLE_KEY].strip(),
                                               f"metadata {ONNX_SIZE_MULTIPLE_KEY!r}")
            except InputError as exc:
                raise FormatError(exc.problem, path) from None
        #: Heights and widths the graph takes are multiples of this (see the class notes).
        self.size_multiple = 1 if size_multiple is None else check_multiple(size_multiple)
        if wavelengths is None:
            if "wavelengths" in meta:
                try:
                    wavelengths = [float(v) for v in meta["wavelengths"].replace(";", ",").split(",")]
                except ValueError:
                    raise FormatError("metadata 'wavelengths' is not a list of numbers", path) from None
        self._declared = None if wavelengths is None else np.asarray(wavelengths, dtype=np.float64)
        self.wavelengths = WAVELENGTHS_31 if self._declared is None else self._declared
        spectra = self._spectra_output(output)
        self.output_name = spectra.name
        self._run_outputs = [spectra.name]
        self.output_layout = _output_layout(spectra.shape, self.fixed_size)
        outputs = self.session.get_outputs()
        self._which = ("" if len(outputs) == 1 else
                       f" (output {spectra.name!r} of {len(outputs)}: "
                       f"{', '.join(o.name for o in outputs)})")
        self.description = f"ONNX model {path.name} ({self.layout})"

    def _spectra_output(self, name: str | None):
        """The graph output that holds the spectra: ``name``, the only one, or the only one
        whose declared shape can hold the band cube.

        Taking the first of several was silent: a graph that also returns an auxiliary map
        first (or a cube-shaped feature map) was scored on that map.
        """
        outputs = self.session.get_outputs()
        listed = ", ".join(f"{o.name!r} {list(o.shape) if o.shape is not None else '?'}"
                           for o in outputs)
        if name is not None:
            hit = [o for o in outputs if o.name == name]
            if not hit:
                raise FormatError(f"the graph has no output {name!r} (its outputs: {listed})",
                                  self.path)
            return hit[0]
        if len(outputs) == 1:
            return outputs[0]
        nb = 31 if self._declared is None else self._declared.size
        fits = [o for o in outputs if _could_be_cube(o.shape, nb, self.fixed_size)]
        if len(fits) == 1:
            return fits[0]
        why = ("several could hold" if fits else "none has a declared shape that can hold")
        raise FormatError(f"the graph has {len(outputs)} outputs ({listed}) and {why} the "
                          f"{nb}-band spectra: name the one that does with output= or "
                          f'{{"output": "NAME"}} in {self.path.name}{SIDECAR_SUFFIX}', self.path)

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
        """The graph on the whole of ``rgb (H, W, 3)``, padded to its size multiple."""
        from mehs.ssr.tiling_pad import call_padded, size_multiple

        k = size_multiple(self)
        if k > 1 and not any(self.fixed_size):
            return call_padded(self._run_graph, rgb, k, self.name)
        return self._run_graph(rgb)

    def _run_graph(self, rgb: np.ndarray) -> np.ndarray:
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
                             "by 8, 16 or 32 must pad inside itself (as MST++'s does) or "
                             "say so: size_multiple= (or the tiling option, or metadata "
                             "'mehs_size_multiple')", self.path) from None
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
