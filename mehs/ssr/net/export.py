"""The trained networks as toolkit SSR models, and their ONNX export.

- :class:`TorchSSRModel` wraps a network in the model contract
  (``rgb float32 (H, W, 3) linear → float32 (H, W, 31)``): the network applies
  its own Reinhard pre-processing (if it was trained with it) and, for the
  ``hdrssr`` variant, its standard spectrum ``S`` is luminance-restored with the
  evaluation module's :func:`mehs.ssr.luminance.restore_luminance`.
  Callers must therefore pass *unprocessed* linear RGB and must not restore
  the luminance a second time (the attributes ``preprocessing`` and
  ``restores_luminance`` say so).
- :func:`export_onnx` writes one self-contained ONNX graph doing the same
  (Reinhard → network → luminance restoration, a torch copy of the evaluation
  function with the same guard), input ``rgb`` ``(N, 3, H, W)`` float32 with
  dynamic N, H, W, output ``spectra`` ``(N, 31, H, W)``, metadata property
  ``wavelengths`` (comma-separated nm); ``mehs.ssr.models.load_model("x.onnx")``
  runs it with onnxruntime.

A network that takes only heights and widths divisible by ``k`` (it down-samples and
does not pad itself) says so with a ``size_multiple = k`` attribute: the models pad
each call to the multiple and crop back (:mod:`mehs.ssr.tiling_pad`), and the ONNX
export carries it as the metadata property ``mehs_size_multiple``.
"""

from __future__ import annotations

import json
import warnings
from pathlib import Path

import numpy as np
import torch
from torch import nn

from mehs import __version__
from mehs.errors import FormatError, InputError, MehsError, first_line
from mehs.io.atomic import atomic_path
from mehs.rgb import WAVELENGTHS_31
from mehs.ssr.contract import SSRModel, TrainedFor
from mehs.ssr.preprocess import PAPER_PREPROCESSING, Preprocessing
from mehs.ssr.registry import get_architecture
from mehs.ssr.net.train import read_checkpoint, resolve_device


def checkpoint_arch(state: dict) -> str:
    """The architecture name a checkpoint records (``arch``; older ones: ``variant``)."""
    arch = state.get("arch") or state.get("variant") or (state.get("net_config") or {}).get("variant")
    if not arch:
        raise FormatError("the checkpoint names no architecture ('arch')")
    return str(arch)


def checkpoint_trained_for(state: dict, network) -> TrainedFor:
    """The checkpoint's ``trained_for`` record, or one derived from an older checkpoint.

    Checkpoints without it: ``net_config.reinhard`` with ``reinhard_scale`` s (the
    network computes ``x/s / (1 + x/s)``; absent: 1, the paper's x/(1+x)) →
    ``Preprocessing(key=None, scale=1/s)``; ``network.predicts_standard_spectrum`` →
    output shape (else spectra); ``net_config.input``, else ``extra.input`` → the
    trained input.
    """
    if isinstance(state.get("trained_for"), dict):
        return TrainedFor.from_dict(state["trained_for"])
    nc = state.get("net_config") or {}
    inp = nc.get("input") or (state.get("extra") or {}).get("input")
    pp = None
    if nc.get("reinhard"):
        s = float(nc.get("reinhard_scale", 1.0) or 1.0)
        pp = PAPER_PREPROCESSING if s == 1.0 else Preprocessing(key=None, scale=1.0 / s)
    return TrainedFor(input=inp if inp in ("hdr", "ldr") else None, preprocessing=pp,
                      output="shape" if getattr(network, "predicts_standard_spectrum", False)
                      else "spectra")


def load_checkpoint_network(path: str | Path, map_location="cpu"):
    """Rebuild the network of a checkpoint through the registry; ``(network, state)``, eval mode."""
    state = read_checkpoint(path, map_location)
    arch = checkpoint_arch(state)
    try:
        net = get_architecture(arch).build(dict(state.get("net_config") or {}))
    except InputError as exc:
        raise exc.with_path(path) from None
    try:
        net.load_state_dict(state["model"])
    except (RuntimeError, KeyError) as exc:
        raise FormatError(f"checkpoint weights do not fit its {arch!r} configuration ({exc})",
                          path) from None
    net.eval()
    return net, state


class TorchSSRModel(SSRModel):
    """A network in the SSR model contract.

    Parameters
    ----------
    network
        A torch module built by a registered architecture (put in eval mode);
        ``forward(rgb (N, 3, H, W))`` applies its own pre-processing.
    name
        Model name in tables (default: the architecture).
    device
        Torch device for inference.
    trained_for
        What it was trained for (default: derived from the network, see
        :func:`checkpoint_trained_for`).
    arch
        The registered architecture name.
    size_multiple
        Heights and widths the network takes are multiples of this (default: the
        network's ``size_multiple`` attribute, else 1); every call is padded to it.
    """

    applies_preprocessing = True

    def __init__(self, network, *, name: str | None = None, device: str = "cpu",
                 source: str | None = None, trained_for: TrainedFor | None = None,
                 arch: str | None = None, size_multiple: int | None = None):
        self.device = resolve_device(device)
        self.network = network.to(self.device).eval()
        cfg = getattr(network, "config", None)
        self.arch = arch or getattr(cfg, "variant", None) or type(network).__name__.lower()
        self.name = name or self.arch
        self.wavelengths = np.asarray(network.wavelengths, dtype=np.float64)
        self.trained_for = trained_for or checkpoint_trained_for(
            {"net_config": cfg.to_dict() if hasattr(cfg, "to_dict") else {}}, network)
        self.source = source
        from mehs.ssr.tiling_pad import declared_multiple

        self.size_multiple = declared_multiple(size_multiple, network,
                                               what=f"{self.name}: size_multiple")
        self.description = (f"{self.arch}: {self.trained_for.label()}"
                            + (f", {Path(source).name}" if source else ""))

    # older attribute names, still read by callers of the first network release
    @property
    def preprocessing(self):
        return self.trained_for.preprocessing.method if self.trained_for.preprocessing else None

    @property
    def restores_luminance(self) -> bool:
        return self.trained_for.output == "shape"

    def on_device(self, device: str) -> "TorchSSRModel":
        """The same network as a model on ``device`` (for timing on CUDA)."""
        import copy

        return TorchSSRModel(copy.deepcopy(self.network), name=self.name, device=device,
                             source=self.source, trained_for=self.trained_for, arch=self.arch,
                             size_multiple=self.size_multiple)

    @torch.no_grad()
    def standard_spectrum(self, rgb: np.ndarray) -> np.ndarray:
        """The network's raw output ``(H, W, B)`` float32 (a shape S for ◇ networks)."""
        rgb = np.asarray(rgb, dtype=np.float32)
        if not np.all(np.isfinite(rgb)):
            raise InputError(f"{self.name}: input RGB has NaN/inf values")
        # the whole image, or tiles with a measured margin when it would not fit in
        # memory (mehs.ssr.tiling); purely local networks too (HSCNN-D on fixed 512²
        # tiles, whatever the memory and the model's tiling, held 2.7 GB for 1024×512
        # under a 1 GB cap)
        from mehs.ssr.tiling_torch import tiled_torch_call

        return np.asarray(tiled_torch_call(self, rgb), dtype=np.float32)

    def predict(self, rgb: np.ndarray) -> np.ndarray:
        """``rgb`` float32 ``(H, W, 3)`` linear → float32 ``(H, W, B)`` spectra."""
        y = self.standard_spectrum(rgb)
        if self.restores_luminance:
            from mehs.ssr.luminance import restore_luminance

            y = restore_luminance(y, rgb, self.wavelengths, overwrite=True)
        return y.astype(np.float32, copy=False)


def is_torchscript(path: str | Path) -> bool:
    """True if ``path`` is a TorchScript archive (``torch.jit.save``): a zip with ``code/``."""
    import zipfile

    try:
        with zipfile.ZipFile(path) as zf:
            return any("/code/" in n or n.startswith("code/") for n in zf.namelist())
    except (OSError, zipfile.BadZipFile):
        return False


class TorchScriptModel(SSRModel):
    """A TorchScript SSR network (``torch.jit.save``) from anywhere, in the model contract.

    The PyTorch convention of the public SSR code (MST++, AWAN, HSCNN+): input
    ``(1, 3, H, W)`` linear RGB, output ``(1, B, H, W)``. The module runs in eval mode
    (dropout and batch-norm statistics off: a module saved while training would
    otherwise answer differently on every call), without autograd, on ``device``, in
    the dtype of its parameters. Bands: ``wavelengths=``, else the module's
    ``wavelengths`` attribute, else 400:700:10 when B = 31. It declares nothing: give it
    ``trained_for`` to be scored only where it was trained. A module that takes only
    sizes divisible by ``k`` (``size_multiple=``, else its ``size_multiple`` attribute)
    gets each image reflect-padded to the multiple and its output cropped back.
    """

    def __init__(self, path: str | Path, *, name: str | None = None, device: str = "cpu",
                 wavelengths=None, size_multiple: int | None = None):
        path = Path(path)
        self.device = resolve_device(device)
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", DeprecationWarning)  # torch ≥ 2.9 on jit
                self.module = torch.jit.load(str(path), map_location=self.device)
        except Exception as exc:  # torch raises several unrelated types for damaged files
            raise FormatError(f"not a loadable TorchScript archive ({type(exc).__name__}: "
                              f"{first_line(exc)})", path) from None
        self.module.eval()
        self.path = path
        self.name = name or path.stem
        params = list(self.module.parameters())
        self.dtype = params[0].dtype if params and params[0].is_floating_point() else torch.float32
        wl = wavelengths if wavelengths is not None else getattr(self.module, "wavelengths", None)
        self._declared = None if wl is None else np.asarray(
            wl.cpu().numpy() if isinstance(wl, torch.Tensor) else wl, dtype=np.float64).reshape(-1)
        self.wavelengths = WAVELENGTHS_31 if self._declared is None else self._declared
        from mehs.ssr.tiling_pad import declared_multiple

        self.size_multiple = declared_multiple(size_multiple, self.module,
                                               what=f"{self.name}: size_multiple")
        self.description = f"TorchScript model {path.name} (NCHW)"

    def on_device(self, device: str) -> "TorchScriptModel":
        """The same module as a model on ``device`` (for timing on CUDA)."""
        return TorchScriptModel(self.path, name=self.name, device=device,
                                wavelengths=self._declared, size_multiple=self.size_multiple)

    def predict(self, rgb: np.ndarray) -> np.ndarray:
        """``rgb (H, W, 3)`` → ``(H, W, B)``; in overlapping tiles when the image would not
        fit the memory budget (:mod:`mehs.ssr.tiling`, ``tiling`` as for
        :class:`TorchSSRModel`): the probes run the module through :attr:`network`."""
        from mehs.ssr.tiling_pad import call_padded, size_multiple
        from mehs.ssr.tiling_torch import tiled_torch_call

        rgb = np.asarray(rgb, dtype=np.float32)
        if not self.__dict__.get("_untileable"):
            try:
                return np.asarray(tiled_torch_call(self, rgb, whole=self._predict_whole),
                                  dtype=np.float32)
            except MehsError:
                raise                       # a tile's own (from _predict_whole), or ours
            except (RuntimeError, AttributeError, IndexError, TypeError, ValueError) as exc:
                if "memory" in str(exc).lower():
                    raise
                # the probes run the module on sizes of their own (96², 384×256, …),
                # which a module that takes only some sizes refuses, and read its output
                # as a tensor (a dict or a 3-D output fails there); the tiles themselves go
                # through _predict_whole, whose errors are InputErrors, and so does the
                # whole image below
                self._untileable = True
                warnings.warn(f"{self.name}: its tiling probes cannot run the module "
                              f"({first_line(exc)}); it runs on whole images (a module that "
                              "takes only sizes divisible by k: size_multiple=k)",
                              RuntimeWarning, stacklevel=2)
        return call_padded(self._predict_whole, rgb, size_multiple(self), self.name)

    @property
    def network(self) -> "torch.nn.Module":
        """The module as the tiling probes run it: ``(1, 3, H, W)`` float32 in, its first
        output as float32 out."""
        if self.__dict__.get("_network") is None:
            self._network = _FirstOutput(self.module, self.dtype).eval()
        return self._network

    @torch.no_grad()
    def _predict_whole(self, rgb: np.ndarray) -> np.ndarray:
        h, w = rgb.shape[:2]
        x = torch.from_numpy(np.ascontiguousarray(rgb.transpose(2, 0, 1))[None])
        try:
            y = self.module(x.to(self.device, self.dtype))
        except RuntimeError as exc:
            if "memory" in str(exc).lower():
                raise  # the timing reads allocation failures
            raise InputError(f"{self.name}: the TorchScript module fails on a {h}×{w} image "
                             f"({first_line(exc)})", self.path) from None
        if isinstance(y, (tuple, list)):
            y = y[0]  # the main output first, as MST++/AWAN return it
        if not isinstance(y, torch.Tensor) or y.ndim != 4 or y.shape[0] != 1 \
                or tuple(y.shape[2:]) != (h, w):
            got = tuple(y.shape) if isinstance(y, torch.Tensor) else type(y).__name__
            raise InputError(f"{self.name}: output {got} is not (1, B, {h}, {w}) for the "
                             f"{h}×{w} input (a module that pads must crop its output "
                             "itself)", self.path)
        if self._declared is not None and y.shape[1] != self._declared.size:
            raise InputError(f"{self.name}: the module gives {y.shape[1]} bands, but "
                             f"{self._declared.size} wavelengths are declared for it", self.path)
        if self._declared is None and y.shape[1] != 31:
            raise InputError(f"{self.name}: the module gives {y.shape[1]} bands; declare them "
                             "with wavelengths= or a 'wavelengths' attribute", self.path)
        return y[0].permute(1, 2, 0).float().cpu().numpy()


class _FirstOutput(nn.Module):
    """A module's first output (MST++ and AWAN return tuples), in float32, its input cast
    to the module's float type."""

    def __init__(self, module, dtype):
        super().__init__()
        self.module, self.dtype = module, dtype

    def forward(self, x):
        y = self.module(x.to(self.dtype))
        if isinstance(y, (tuple, list)):
            y = y[0]
        return y.float()


def load_torch_model(checkpoint: str | Path, *, name: str | None = None,
                     device: str = "cpu", wavelengths=None):
    """A :class:`TorchSSRModel` from a training checkpoint (``last.pt`` / ``best.pt``).

    The network is rebuilt by the architecture the checkpoint names
    (:func:`mehs.ssr.registry.get_architecture`). ``wavelengths``, if given,
    must be the network's own bands; ``load_model("x.pt", ...)`` lands here.
    A TorchScript archive gives a :class:`TorchScriptModel`.
    """
    if Path(checkpoint).is_file() and is_torchscript(checkpoint):
        return TorchScriptModel(checkpoint, name=name, device=device, wavelengths=wavelengths)
    try:
        net, state = load_checkpoint_network(checkpoint, map_location="cpu")
    except FormatError as exc:
        if _bare_weights(checkpoint):
            raise FormatError(f"{exc.problem}: it holds bare weights (a state_dict) without "
                              "the network that uses them; save the model with "
                              "torch.jit.save(torch.jit.script(model)) or export it to ONNX, "
                              "and name that file", checkpoint) from None
        raise
    net_wl = np.asarray(net.wavelengths, dtype=np.float64)
    if wavelengths is not None:
        want = np.asarray(wavelengths, dtype=np.float64).reshape(-1)
        if want.shape != net_wl.shape or not np.allclose(want, net_wl, atol=0.01):
            raise InputError(f"the network predicts {net_wl.size} bands "
                             f"{net_wl[0]:g}..{net_wl[-1]:g} nm, not the "
                             f"{want.size} requested", checkpoint)
    return TorchSSRModel(net, name=name, device=device, source=str(checkpoint),
                         trained_for=checkpoint_trained_for(state, net),
                         arch=checkpoint_arch(state))


def _bare_weights(path: str | Path) -> bool:
    """True if ``path`` holds a plain state_dict (or ``{"state_dict": ...}``), not a checkpoint."""
    try:
        state = torch.load(path, map_location="cpu", weights_only=True)
    except Exception:  # noqa: BLE001 - unreadable: the first error says so
        return False
    if isinstance(state, dict) and isinstance(state.get("state_dict"), dict):
        state = state["state_dict"]
    return (isinstance(state, dict) and bool(state) and "format" not in state
            and all(isinstance(v, torch.Tensor) for v in state.values()))


class _ContractGraph(nn.Module):
    """The exported graph: linear RGB ``(N, 3, H, W)`` → spectra ``(N, B, H, W)``."""

    def __init__(self, network):
        super().__init__()
        self.network = network

    def forward(self, rgb: torch.Tensor) -> torch.Tensor:
        return self.network.spectra(rgb)


def export_onnx(model, path: str | Path, *, opset: int = 17, example_size=(64, 48),
                size_multiple: int | None = None) -> Path:
    """Export a network (or a checkpoint path, or a :class:`TorchSSRModel`) to ONNX, atomically.

    The TorchScript-based exporter is used (``dynamo=False``): it needs no
    package beyond torch and keeps H and W dynamic, including the padding to a
    multiple of ``2**depth`` done inside the network. A network that does not pad
    itself declares ``size_multiple`` (argument, else the model's or network's
    attribute): the trace example is rounded up to it and the graph carries it as
    the metadata property ``mehs_size_multiple``, which :class:`~mehs.ssr.models.OnnxModel`
    pads every run to.
    """
    from mehs.ssr.tiling_pad import ONNX_SIZE_MULTIPLE_KEY, declared_multiple

    wrapper = None if isinstance(model, (str, Path)) else model   # its own multiple first
    tf, tf_arch = None, None
    if isinstance(model, (str, Path)):
        model, state = load_checkpoint_network(model)
        tf, tf_arch = checkpoint_trained_for(state, model), checkpoint_arch(state)
    elif isinstance(model, TorchSSRModel):
        tf, tf_arch = model.trained_for, model.arch
        model = model.network
    if tf is None:
        cfg = getattr(model, "config", None)
        tf = checkpoint_trained_for({"net_config": cfg.to_dict() if hasattr(cfg, "to_dict")
                                     else {}}, model)
        tf_arch = getattr(cfg, "variant", type(model).__name__.lower())
    if not hasattr(model, "spectra"):
        raise InputError(f"cannot export {type(model).__name__}: not an SSR network")
    _require_onnx()
    k = declared_multiple(size_multiple, wrapper, model)
    net = model.to("cpu").eval()
    graph = _ContractGraph(net).eval()
    example = torch.rand(1, 3, *(-(-int(n) // k) * k for n in example_size))
    path = Path(path)
    with atomic_path(path) as tmp:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # the exporter's deprecation and tracer notes
            torch.onnx.export(graph, (example,), str(tmp), dynamo=False, opset_version=opset,
                              input_names=["rgb"], output_names=["spectra"],
                              dynamic_axes={"rgb": {0: "batch", 2: "height", 3: "width"},
                                            "spectra": {0: "batch", 2: "height", 3: "width"}})
        _add_metadata(tmp, {
            "wavelengths": ",".join(f"{w:g}" for w in net.wavelengths),
            "mehs_variant": tf_arch,
            "mehs_preprocessing": "reinhard" if tf.preprocessing else "none",
            "mehs_luminance_restored": "true" if tf.output == "shape" else "false",
            "mehs_trained_for": json.dumps(tf.to_dict()),
            "mehs_version": __version__,
            **({ONNX_SIZE_MULTIPLE_KEY: str(k)} if k > 1 else {}),
        })
    return path


ONNX_HINT = 'pip install "mehs[onnx]"'


def _require_onnx() -> None:
    """Refuse before exporting: torch's exporter needs the ``onnx`` package (torch extra alone
    lacks it) and would otherwise fail with its own ``OnnxExporterError`` after the trace."""
    import importlib.util

    try:
        found = importlib.util.find_spec("onnx") is not None
    except ValueError:  # a module set to None in sys.modules (tests) or half-imported
        found = False
    if not found:
        raise InputError(f"ONNX export needs the onnx package, which is not installed "
                         f"({ONNX_HINT})")


def _add_metadata(path: Path, props: dict[str, str]) -> None:
    try:
        import onnx
    except ImportError:  # metadata is a convenience: 31 bands are the default anyway
        return
    m = onnx.load(str(path))
    for k, v in props.items():
        entry = m.metadata_props.add()
        entry.key, entry.value = k, v
    onnx.save(m, str(path))
