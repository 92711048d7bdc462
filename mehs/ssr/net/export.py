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
"""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np
import torch
from torch import nn

from mehs import __version__
from mehs.errors import InputError
from mehs.io.atomic import atomic_path
from mehs.ssr.models import SSRModel
from mehs.ssr.net.train import load_network, resolve_device


class TorchSSRModel(SSRModel):
    """A network in the SSR model contract.

    Parameters
    ----------
    network
        An :class:`~mehs.ssr.net.model.HDRSSRNet` or
        :class:`~mehs.ssr.net.model.FCDenseNetSSR` (put in eval mode).
    name
        Model name in tables (default: the variant).
    device
        Torch device for inference.
    """

    def __init__(self, network, *, name: str | None = None, device: str = "cpu",
                 source: str | None = None):
        self.device = resolve_device(device)
        self.network = network.to(self.device).eval()
        self.name = name or network.config.variant
        self.wavelengths = network.wavelengths
        self.preprocessing = "reinhard" if network.config.reinhard else None
        self.restores_luminance = bool(network.predicts_standard_spectrum)
        self.source = source
        what = ("FC-DenseNet + basis branches, learns spectral similarity"
                if self.restores_luminance else "FC-DenseNet end to end")
        self.description = f"{what}{' (Reinhard input)' if self.preprocessing else ''}" + (
            f", {Path(source).name}" if source else "")

    @torch.no_grad()
    def predict(self, rgb: np.ndarray) -> np.ndarray:
        """``rgb`` float32 ``(H, W, 3)`` linear → float32 ``(H, W, B)``."""
        if not np.all(np.isfinite(rgb)):
            raise InputError(f"{self.name}: input RGB has NaN/inf values")
        from mehs.ssr.tiling import tiled_torch_call

        y = tiled_torch_call(self, rgb)  # whole image, or tiles when it would not fit in memory
        if self.restores_luminance:
            from mehs.ssr.luminance import restore_luminance

            y = restore_luminance(y, rgb, self.wavelengths)
        return y.astype(np.float32, copy=False)


def load_torch_model(checkpoint: str | Path, *, name: str | None = None,
                     device: str = "cpu", wavelengths=None) -> TorchSSRModel:
    """A :class:`TorchSSRModel` from a training checkpoint (``last.pt`` / ``best.pt``).

    ``wavelengths``, if given, must be the network's own bands (a network cannot
    be asked for others); ``mehs.ssr.models.load_model("x.pt", ...)`` lands here.
    """
    net, _ = load_network(checkpoint, map_location="cpu")
    if wavelengths is not None:
        want = np.asarray(wavelengths, dtype=np.float64).reshape(-1)
        if want.shape != net.wavelengths.shape or not np.allclose(want, net.wavelengths, atol=0.01):
            raise InputError(f"the network predicts {net.wavelengths.size} bands "
                             f"{net.wavelengths[0]:g}..{net.wavelengths[-1]:g} nm, not the "
                             f"{want.size} requested", checkpoint)
    return TorchSSRModel(net, name=name, device=device, source=str(checkpoint))


class _ContractGraph(nn.Module):
    """The exported graph: linear RGB ``(N, 3, H, W)`` → spectra ``(N, B, H, W)``."""

    def __init__(self, network):
        super().__init__()
        self.network = network

    def forward(self, rgb: torch.Tensor) -> torch.Tensor:
        return self.network.spectra(rgb)


def export_onnx(model, path: str | Path, *, opset: int = 17, example_size=(64, 48)) -> Path:
    """Export a network (or a checkpoint path, or a :class:`TorchSSRModel`) to ONNX, atomically.

    The TorchScript-based exporter is used (``dynamo=False``): it needs no
    package beyond torch and keeps H and W dynamic, including the padding to a
    multiple of ``2**depth`` done inside the network.
    """
    if isinstance(model, (str, Path)):
        model, _ = load_network(model)
    elif isinstance(model, TorchSSRModel):
        model = model.network
    if not hasattr(model, "spectra"):
        raise InputError(f"cannot export {type(model).__name__}: not an SSR network")
    net = model.to("cpu").eval()
    graph = _ContractGraph(net).eval()
    example = torch.rand(1, 3, *example_size)
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
            "mehs_variant": net.config.variant,
            "mehs_preprocessing": "reinhard" if net.config.reinhard else "none",
            "mehs_luminance_restored": "true" if net.predicts_standard_spectrum else "false",
            "mehs_version": __version__,
        })
    return path


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
