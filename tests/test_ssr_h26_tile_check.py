"""Tiles checked on a probe image before they are trusted (issue 16, session 26).

A network that is not shift-equivariant on its grid — a bilinear up-sampling to the
input's size with ``align_corners=True`` — shows a local field and a plain grid to every
probe, and its tiles were 7.9e-2 of the range off the whole image without a word.
"""

from __future__ import annotations

import warnings
from types import SimpleNamespace

import numpy as np
import pytest

torch = pytest.importorskip("torch")
F = torch.nn.functional


class TwoResolutions(torch.nn.Module):
    """An HRNet-like pair of branches, the coarse one up-sampled to the input's size."""

    def __init__(self, align_corners: bool):
        super().__init__()
        self.align_corners = align_corners
        self.a = torch.nn.Conv2d(3, 8, 3, padding=1)
        self.d = torch.nn.Conv2d(8, 8, 3, stride=2, padding=1)
        self.o = torch.nn.Conv2d(16, 31, 3, padding=1)

    def forward(self, x):
        y = torch.tanh(self.a(x))
        z = F.interpolate(torch.tanh(self.d(y)), size=x.shape[-2:], mode="bilinear",
                          align_corners=self.align_corners)
        return self.o(torch.cat([y, z], 1))


def _tiled(net, rgb):
    from mehs.ssr.tiling_torch import tiled_torch_call

    model = SimpleNamespace(network=net, device="cpu", name="hr", tiling=dict(
        bytes_per_pixel=1.0, max_bytes=200 * 200, blend=8))
    return tiled_torch_call(model, rgb), model


def test_tiles_of_a_network_that_is_not_shift_equivariant_are_warned_about():
    torch.manual_seed(0)
    rgb = np.random.default_rng(0).random((320, 512, 3), dtype=np.float32)
    with pytest.warns(RuntimeWarning, match="not shift-equivariant"):
        _, model = _tiled(TwoResolutions(True).eval(), rgb)
    assert model._tiling_probe["tiles_check_diff"] > 1e-3
    assert model._tiling_last["summary"]["tiles"] >= 2      # the call's record, not the probe's


def test_tiles_of_an_equivariant_network_pass_the_check_once():
    torch.manual_seed(0)
    net = TwoResolutions(False).eval()
    rgb = np.random.default_rng(0).random((320, 512, 3), dtype=np.float32)
    with warnings.catch_warnings():
        warnings.simplefilter("error", RuntimeWarning)
        tiled, model = _tiled(net, rgb)
    assert model._tiling_probe["tiles_check_diff"] < 1e-5
    calls = []
    net.register_forward_pre_hook(lambda m, i: calls.append(i[0].shape))
    from mehs.ssr.tiling_torch import tiled_torch_call

    tiled_torch_call(model, rgb)
    assert len(calls) == model._tiling_last["summary"]["tiles"]        # checked once


def test_an_onnx_graph_that_is_not_shift_equivariant_is_warned_about(tmp_path):
    pytest.importorskip("onnx")
    pytest.importorskip("onnxruntime")
    from mehs.ssr.models import OnnxModel

    torch.manual_seed(1)
    path = tmp_path / "hr.onnx"
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        torch.onnx.export(TwoResolutions(True).eval(), (torch.rand(1, 3, 64, 64),), str(path),
                          dynamo=False, input_names=["rgb"], output_names=["spectra"],
                          dynamic_axes={"rgb": {2: "h", 3: "w"}, "spectra": {2: "h", 3: "w"}})
    model = OnnxModel(path)
    model.tiling = {"bytes_per_pixel": 1000.0, "max_bytes": 1000 * 200 ** 2}
    rgb = np.random.default_rng(1).random((320, 512, 3), dtype=np.float32)
    with pytest.warns(RuntimeWarning, match="not shift-equivariant"):
        model.predict(rgb)
