"""TorchScript models run in tiles when memory is short (issue 16, session 26).

A user's TorchScript archive (``torch.jit.save``; the usual way to ship MST++, AWAN or
HSCNN+ weights with their code) always ran on the whole image: a 2048×1024 image through
MST++ held 4.4 GB, whatever the memory budget said.
"""

from __future__ import annotations

import warnings

import numpy as np
import pytest

torch = pytest.importorskip("torch")
nn, F = torch.nn, torch.nn.functional


class UNet(nn.Module):
    """``levels`` poolings; ``pad``: padding itself to its grid, else taking only its
    multiples (and declaring nothing)."""

    def __init__(self, levels: int = 3, pad: bool = True):
        super().__init__()
        self.m, self.pad = 2 ** levels, pad
        self.inc = nn.Conv2d(3, 8, 3, padding=1)
        self.down = nn.ModuleList(nn.Conv2d(8, 8, 3, padding=1) for _ in range(levels))
        self.out = nn.Conv2d(8, 31, 3, padding=1)

    def forward(self, x):
        h, w = x.shape[-2], x.shape[-1]
        if self.pad:
            m = self.m
            x = F.pad(x, [0, (m - w % m) % m, 0, (m - h % m) % m], mode="replicate")
        y = torch.relu(self.inc(x))
        skips = []
        for d in self.down:
            skips.append(y)
            y = F.avg_pool2d(torch.tanh(d(y)), 2)
        for s in skips[::-1]:
            y = F.interpolate(y, scale_factor=2.0, mode="nearest") + s
        return self.out(y)[:, :, :h, :w]


class Pair(nn.Module):
    """A tuple out, as MST++'s and AWAN's public code gives."""

    def __init__(self):
        super().__init__()
        self.net = UNet()

    def forward(self, x):
        y = self.net(x)
        return y, y.mean()


def _save(net, path):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecationWarning)    # torch ≥ 2.9 on jit
        torch.jit.save(torch.jit.script(net.eval()), str(path))
    return path


@pytest.mark.parametrize("pair", [False, True])
def test_a_torchscript_model_is_tiled_to_its_budget(tmp_path, pair):
    from mehs.ssr.net.export import TorchScriptModel

    torch.manual_seed(0)
    model = TorchScriptModel(_save(Pair() if pair else UNet(), tmp_path / "unet.pt"))
    rgb = np.random.default_rng(0).random((256, 600, 3), dtype=np.float32)
    model.tiling = "off"
    whole = model.predict(rgb)
    model.tiling = {"bytes_per_pixel": 1000.0, "max_bytes": 1000 * 200 ** 2}
    tiled = model.predict(rgb)
    last = model._tiling_last
    assert last["summary"]["tiles"] >= 3
    assert model._tiling_probe["align"] == 8 and model._tiling_probe["margin"] > 0
    np.testing.assert_allclose(tiled, whole, rtol=0, atol=1e-5 * np.abs(whole).max())


def test_a_tiled_torchscript_model_keeps_its_checks(tmp_path):
    from mehs.errors import InputError
    from mehs.ssr.net.export import TorchScriptModel

    class Five(nn.Module):
        def forward(self, x):
            return x[:, :1].repeat(1, 5, 1, 1)

    model = TorchScriptModel(_save(Five(), tmp_path / "five.pt"))
    model.tiling = {"bytes_per_pixel": 1000.0, "max_bytes": 1000 * 200 ** 2}
    with pytest.raises(InputError, match="gives 5 bands"):
        model.predict(np.zeros((256, 600, 3), np.float32))


def test_a_module_that_takes_only_some_sizes_still_runs_whole(tmp_path):
    # the tiling probes run it on sizes of their own (96²): a raw TorchScript error where
    # it ran whole before
    from mehs.errors import InputError
    from mehs.ssr.net.export import TorchScriptModel

    torch.manual_seed(2)
    path = _save(UNet(6, pad=False), tmp_path / "m64.pt")    # multiples of 64 only
    model = TorchScriptModel(path)
    rgb = np.random.default_rng(2).random((512, 512, 3), dtype=np.float32)
    with pytest.warns(RuntimeWarning, match="tiling probes cannot run"):
        out = model.predict(rgb)
    assert out.shape == (512, 512, 31)
    model.tiling = "off"
    np.testing.assert_array_equal(model.predict(rgb), out)
    with pytest.raises(InputError, match="fails on a 500×500 image"), \
            pytest.warns(RuntimeWarning, match="tiling probes cannot run"):
        TorchScriptModel(path).predict(np.zeros((500, 500, 3), np.float32))


def test_a_module_with_a_malformed_output_still_gets_a_clear_error(tmp_path):
    # the probes read its output as a tensor: a raw AttributeError ('dict' has no
    # 'float') where whole-image runs name the problem
    from typing import Dict

    from mehs.errors import InputError
    from mehs.ssr.net.export import TorchScriptModel

    class AsDict(nn.Module):
        def forward(self, x) -> Dict[str, torch.Tensor]:
            return {"spectra": x.repeat(1, 11, 1, 1)[:, :31]}

    model = TorchScriptModel(_save(AsDict(), tmp_path / "dict.pt"))
    with pytest.raises(InputError, match="is not \\(1, B, 512, 600\\)"), \
            pytest.warns(RuntimeWarning, match="tiling probes cannot run"):
        model.predict(np.zeros((512, 600, 3), np.float32))
