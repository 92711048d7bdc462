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
    """An HRNet-like pair of branches, the coarse one up-sampled to the input's size;
    ``stride=(2, 1)``: coarse along the rows only; ``se``: a global average pooling gate."""

    def __init__(self, align_corners: bool, stride=2, se: bool = False):
        super().__init__()
        self.align_corners, self.se = align_corners, se
        self.a = torch.nn.Conv2d(3, 8, 3, padding=1)
        self.d = torch.nn.Conv2d(8, 8, 3, stride=stride, padding=1)
        self.e = torch.nn.Conv2d(16, 16, 1)
        self.o = torch.nn.Conv2d(16, 31, 3, padding=1)

    def forward(self, x):
        y = torch.tanh(self.a(x))
        z = F.interpolate(torch.tanh(self.d(y)), size=x.shape[-2:], mode="bilinear",
                          align_corners=self.align_corners)
        f = torch.cat([y, z], 1)
        if self.se:
            f = f * torch.sigmoid(self.e(f.mean((2, 3), keepdim=True)))
        return self.o(f)


def _tiled(net, rgb):
    from mehs.ssr.tiling_torch import tiled_torch_call

    model = SimpleNamespace(network=net, device="cpu", name="hr", tiling=dict(
        bytes_per_pixel=1.0, max_bytes=200 * 200, blend=8))
    return tiled_torch_call(model, rgb), model


@pytest.mark.parametrize("stride", [2, (2, 1)])
def test_tiles_of_a_network_that_is_not_shift_equivariant_are_warned_about(stride):
    # (2, 1): not equivariant along the rows only, which a probe of two tiles side by side
    # passed (1e-8) while the real tiles were 1.3e-1 off
    torch.manual_seed(0)
    net = TwoResolutions(True, stride).eval()
    rgb = np.random.default_rng(0).random((512, 512, 3), dtype=np.float32)
    with pytest.warns(RuntimeWarning, match="not shift-equivariant"):
        _, model = _tiled(net, rgb)
    assert model._tiling_probe["tiles_check_diff"] > 1e-3
    last = model._tiling_last
    assert last["summary"]["tiles"] >= 4 and last["tiles_differ"]   # the call's record
    # and on every call, not the first only
    from mehs.ssr.tiling_torch import tiled_torch_call

    with pytest.warns(RuntimeWarning, match="not shift-equivariant"):
        tiled_torch_call(model, rgb)
    assert model._tiling_last["tiles_differ"]


def test_the_check_keeps_within_a_tile_of_memory(monkeypatch):
    # its whole probe ran 1.86x the pixels of the largest tile the budget allowed
    import mehs.ssr.tiling_check as check

    sizes = []
    probe = check.probe_image
    monkeypatch.setattr(check, "probe_image", lambda h, w: sizes.append(h * w) or probe(h, w))
    torch.manual_seed(0)
    rgb = np.random.default_rng(0).random((512, 768, 3), dtype=np.float32)
    _, model = _tiled(TwoResolutions(False).eval(), rgb)
    plan = model._tiling_last["plan"]
    assert model._tiling_probe["tiles_check_diff"] < 1e-5
    assert len(sizes) == 2 and max(sizes) <= plan.tile * plan.width


def test_tiles_of_an_equivariant_network_pass_the_check_once():
    torch.manual_seed(0)
    net = TwoResolutions(False).eval()
    rgb = np.random.default_rng(0).random((320, 512, 3), dtype=np.float32)
    with warnings.catch_warnings():
        warnings.simplefilter("error", RuntimeWarning)
        tiled, model = _tiled(net, rgb)
    assert model._tiling_probe["tiles_check_diff"] < 1e-5
    calls = []
    # (counted by its forward, not a hook: a hook set since the probes ran may change what
    # they measured, so it has them measured again, session 29)
    forward = net.forward
    net.forward = lambda x: calls.append(x.shape) or forward(x)
    from mehs.ssr.tiling_torch import tiled_torch_call

    tiled_torch_call(model, rgb)
    assert len(calls) == model._tiling_last["summary"]["tiles"]        # checked once


@pytest.mark.parametrize("se", [False, True])
def test_an_onnx_graph_that_is_not_shift_equivariant_is_warned_about(tmp_path, se):
    # se: the image-means probe of a graph with a global average pooling, which also
    # had two tiles side by side only
    pytest.importorskip("onnx")
    pytest.importorskip("onnxruntime")
    from mehs.ssr.models import OnnxModel

    torch.manual_seed(1)
    path = tmp_path / "hr.onnx"
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        torch.onnx.export(TwoResolutions(True, (2, 1), se).eval(), (torch.rand(1, 3, 64, 64),),
                          str(path),
                          dynamo=False, input_names=["rgb"], output_names=["spectra"],
                          dynamic_axes={"rgb": {2: "h", 3: "w"}, "spectra": {2: "h", 3: "w"}})
    model = OnnxModel(path)
    model.tiling = {"bytes_per_pixel": 1000.0, "max_bytes": 1000 * 200 ** 2}
    rgb = np.random.default_rng(1).random((512, 512, 3), dtype=np.float32)
    with pytest.warns(RuntimeWarning, match="not shift-equivariant" if not se else
                      "tiles still differ from the whole image"):
        model.predict(rgb)
