"""Tiled and whole-image inference of networks that take only sizes divisible by k
(session 21): each call padded (reflect) to the multiple, the output cropped back."""

import numpy as np
import pytest

from mehs.errors import InputError
from mehs.rgb import WAVELENGTHS_31
from mehs.ssr.tiling_pad import call_padded, pad_to_multiple, size_multiple

torch = pytest.importorskip("torch")
from torch import nn  # noqa: E402
from torch.nn import functional as F  # noqa: E402

K = 8
#: tiles of about 64×64 (bytes per pixel × pixels), margin and blend chosen to cut
#: a 150×115 image into several tiles whose last ones along each axis are not multiples
TILING = {"bytes_per_pixel": 1000.0, "fixed_bytes": 0.0, "max_bytes": 1000 * 72 * 72,
          "margin": 16, "blend": 8}


class NeedsMultiple(nn.Module):
    """Three stride-2 convolutions, nearest up-sampling ×8 and a skip connection: other
    sizes than multiples of 8 do not fit the skip (and are refused up front)."""

    size_multiple = K
    wavelengths = WAVELENGTHS_31

    def __init__(self):
        super().__init__()
        g = torch.Generator().manual_seed(0)
        self.inp = nn.Conv2d(3, 8, 3, padding=1)
        self.down = nn.ModuleList(nn.Conv2d(8, 8, 3, stride=2, padding=1) for _ in range(3))
        self.out = nn.Conv2d(8, 31, 1)
        with torch.no_grad():
            for p in self.parameters():
                p.copy_(torch.randn(p.shape, generator=g) * 0.3)

    def forward(self, x):
        if not torch.jit.is_tracing() and (x.shape[-2] % K or x.shape[-1] % K):
            raise ValueError(f"needs multiples of {K}, got {tuple(x.shape[-2:])}")
        f = torch.relu(self.inp(x))
        d = f
        for conv in self.down:
            d = torch.relu(conv(d))
        return self.out(f + F.interpolate(d, scale_factor=K, mode="nearest"))

    def spectra(self, x):
        return self.forward(x)


@pytest.fixture(scope="module")
def net():
    return NeedsMultiple().eval()


@pytest.fixture(scope="module")
def rgb():
    rng = np.random.default_rng(3)
    x = rng.gamma(1.0, 0.5, (150, 115, 3)).astype(np.float32)
    x[:, :40] *= 3.0
    return x


def reference(net, rgb):
    """Whole-image inference of the reflect-padded image, cropped: the definition."""
    h, w = rgb.shape[:2]
    x = np.pad(rgb, ((0, -h % K), (0, -w % K), (0, 0)), mode="reflect")
    with torch.no_grad():
        y = net(torch.from_numpy(np.ascontiguousarray(x.transpose(2, 0, 1)))[None])
    return y[0].permute(1, 2, 0).numpy()[:h, :w]


def _close(a, b):
    scale = float(np.abs(b).max())
    assert a.shape == b.shape
    assert float(np.abs(a - b).max()) <= 1e-5 * scale


def test_padding_helpers():
    x = np.arange(5 * 3 * 1, dtype=np.float32).reshape(5, 3, 1)
    p = pad_to_multiple(x, 4)
    assert p.shape == (8, 4, 1) and np.array_equal(p[:5, :3], x)
    assert np.array_equal(p[5:, :3, 0], x[[3, 2, 1], :, 0])        # reflected, edge not repeated
    assert pad_to_multiple(x, 1) is x
    assert pad_to_multiple(np.ones((1, 1, 3), np.float32), 8).shape == (8, 8, 3)
    seen = []
    y = call_padded(lambda t: (seen.append(t.shape), np.repeat(t[..., :1], 31, -1))[1], x, 4)
    assert seen == [(8, 4, 1)] and y.shape == (5, 3, 31)
    with pytest.raises(InputError, match="padded to multiples of 4"):
        call_padded(lambda t: t[:-1], x, 4, "m")

    class M:
        tiling = {"size_multiple": 16}
        size_multiple = 8
    assert size_multiple(M()) == 16
    M.tiling = "auto"
    assert size_multiple(M()) == 8
    M.size_multiple = 0
    with pytest.raises(InputError, match="size_multiple"):
        size_multiple(M())


def test_torch_whole_and_tiled_equal_padded_whole_image(net, rgb):
    from mehs.ssr.net.export import TorchSSRModel

    model = TorchSSRModel(net, name="needs8")
    assert model.size_multiple == K
    want = reference(net, rgb)
    model.tiling = "off"
    _close(model(rgb), want)                         # the network alone refuses 150×115
    model.tiling = dict(TILING)
    got = model(rgb)
    summary = model._tiling_last["summary"]
    assert summary["tiles"] >= 4, summary            # tiled, last tiles not multiples of 8
    assert model._tiling_last["plan"].align % K == 0
    _close(got, want)


def test_onnx_export_carries_the_multiple_and_tiles_equal_whole_image(net, rgb, tmp_path):
    pytest.importorskip("onnxruntime")
    pytest.importorskip("onnx")
    from mehs.ssr.models import OnnxModel, load_model
    from mehs.ssr.net.export import TorchSSRModel, export_onnx

    path = export_onnx(TorchSSRModel(net), tmp_path / "needs8.onnx", example_size=(61, 45))
    model = load_model(str(path))
    assert isinstance(model, OnnxModel) and model.size_multiple == K
    want = reference(net, rgb)
    model.tiling = "off"
    _close(model(rgb), want)
    model.tiling = {**TILING, "align": 8}            # the ONNX default grid is 32
    got = model(rgb)
    assert model._tiling_last["summary"]["tiles"] >= 4
    _close(got, want)
    # the same graph told nothing about its multiple fails on these sizes, naming the option
    plain = OnnxModel(path, size_multiple=1)
    plain.tiling = "off"
    with pytest.raises(InputError, match="size_multiple"):
        plain(rgb)


def test_sidecar_declares_the_multiple_of_a_foreign_graph(net, rgb, tmp_path):
    """A graph from elsewhere carries no mehs metadata: its ``<file>.json`` says k."""
    pytest.importorskip("onnxruntime")
    pytest.importorskip("onnx")
    import json

    import onnx

    from mehs.errors import FormatError
    from mehs.ssr.models import load_model
    from mehs.ssr.net.export import TorchSSRModel, export_onnx

    path = export_onnx(TorchSSRModel(net), tmp_path / "foreign.onnx", example_size=(64, 48))
    g = onnx.load(str(path))
    keep = [p for p in g.metadata_props if p.key != "mehs_size_multiple"]
    del g.metadata_props[:]
    g.metadata_props.extend(keep)
    onnx.save(g, str(path))
    assert load_model(str(path)).size_multiple == 1          # nothing says so: any size
    side = tmp_path / "foreign.onnx.json"
    side.write_text(json.dumps({"size_multiple": K}))
    model = load_model(str(path))
    assert model.size_multiple == K
    model.tiling = "off"
    _close(model(rgb), reference(net, rgb))
    side.write_text(json.dumps({"size_multiple": 2.5}))
    with pytest.raises(FormatError, match=r"foreign\.onnx\.json.*size_multiple"):
        load_model(str(path))
