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


class PooledBelow(NeedsMultiple):
    """:class:`NeedsMultiple` with a channel attention (a global average pooling) on the
    ×8 down-sampled features: a pooled map of ``h / 8`` cells per tile."""

    def __init__(self):
        super().__init__()
        from mehs.ssr.net.layers import ChannelAttention

        self.att = ChannelAttention(8, reduction=2)
        g = torch.Generator().manual_seed(1)
        with torch.no_grad():
            for p in self.att.parameters():
                p.copy_(torch.randn(p.shape, generator=g) * 0.5)

    def forward(self, x):
        if not torch.jit.is_tracing() and (x.shape[-2] % K or x.shape[-1] % K):
            raise ValueError(f"needs multiples of {K}, got {tuple(x.shape[-2:])}")
        f = torch.relu(self.inp(x))
        d = f
        for conv in self.down:
            d = torch.relu(conv(d))
        return self.out(f + F.interpolate(self.att(d), scale_factor=K, mode="nearest"))


#: heights whose last tile is not a multiple of 8 (138: a 42-row last tile padded to 48,
#: whose 6-cell pooled map is 8 rows a cell, not ceil(42 / 6) = 7) and widths
POOLED_SIZES = [(138, 115), (138, 120), (150, 115), (161, 120)]


def _pooled_images():
    rng = np.random.default_rng(5)
    for h, w in POOLED_SIZES:
        x = rng.gamma(1.0, 0.5, (h, w, 3)).astype(np.float32)
        x[:, : w // 3] *= 3.0                      # tiles' own means differ from the image's
        yield x


def test_torch_image_means_with_a_pooling_below_full_resolution():
    from mehs.ssr.net.export import TorchSSRModel

    net = PooledBelow().eval()
    model = TorchSSRModel(net, name="pooled8")
    for rgb in _pooled_images():
        model.tiling = dict(TILING)
        got = model(rgb)
        last = model._tiling_last
        assert last["statistics"] == "image" and last["summary"]["tiles"] >= 4, last
        _close(got, reference(net, rgb))


def test_onnx_image_means_with_a_pooling_below_full_resolution(tmp_path):
    pytest.importorskip("onnxruntime")
    pytest.importorskip("onnx")
    from mehs.ssr.models import load_model
    from mehs.ssr.net.export import TorchSSRModel, export_onnx

    net = PooledBelow().eval()
    path = export_onnx(TorchSSRModel(net), tmp_path / "pooled8.onnx", example_size=(61, 45))
    model = load_model(str(path))
    assert model.size_multiple == K
    for rgb in _pooled_images():
        model.tiling = {**TILING, "align": 8}
        got = model(rgb)
        last = model._tiling_last
        assert last["statistics"] == "image" and last["summary"]["tiles"] >= 4, last
        _close(got, reference(net, rgb))
    assert model._tiling_probe["image_means"] is True


class BlockLocal(nn.Module):
    """Each 8×8 block's spectra from that block alone (space-to-depth, a 1×1 convolution,
    depth-to-space): needs multiples of 8, and tiles on the 8-grid need no margin at all,
    so only the padding of an image's last tile can make them differ from the image."""

    size_multiple = K
    wavelengths = WAVELENGTHS_31

    def __init__(self):
        super().__init__()
        g = torch.Generator().manual_seed(2)
        self.conv = nn.Conv2d(3 * K * K, 31 * K * K, 1)
        with torch.no_grad():
            for p in self.parameters():
                p.copy_(torch.randn(p.shape, generator=g) * 0.1)

    def forward(self, x):
        return F.pixel_shuffle(self.conv(F.pixel_unshuffle(x, K)), K)


def test_last_tile_at_least_the_multiple_with_a_zero_margin():
    """Margin and blend 0 (statistics 'tile'): tiles that do not overlap step by a whole
    tile, so an image's last tile could be 1 row long and reflect-pad within itself
    (73 rows in 24-row tiles: a 1-row last tile) instead of the image's own rows."""
    from mehs.ssr.net.export import TorchSSRModel
    from mehs.ssr.tiling import tile_starts

    net = BlockLocal().eval()
    model = TorchSSRModel(net, name="block8")
    rng = np.random.default_rng(11)
    for h, w in ((73, 37), (100, 52), (57, 81)):
        rgb = rng.gamma(1.0, 0.5, (h, w, 3)).astype(np.float32)
        model.tiling = {"bytes_per_pixel": 1000.0, "fixed_bytes": 0.0,
                        "max_bytes": 1000 * 24 * 24, "margin": 0, "blend": 0,
                        "statistics": "tile", "align": 8}
        got = model(rgb)
        plan = model._tiling_last["plan"]
        assert model._tiling_last["summary"]["tiles"] >= 3
        for n, t in ((h, plan.tile), (w, plan.width)):
            starts = tile_starts(n, t, plan.overlap, plan.align)
            assert len(starts) == 1 or n - starts[-1] >= K, (n, plan)
        _close(got, reference(net, rgb))
