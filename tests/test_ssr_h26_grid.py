"""The tile grid of torch networks that declare none (issue 16, session 26).

Tiles equal whole-image inference only where their edges lie on the network's
down-sampling grid. The grid was read off a ``depth`` attribute (mehs's own networks) and
was 8 for every other network: a user's 5-level U-Net, or a network pooling in cells of
32 through ``torch.nn.functional`` alone, was tiled off its grid and its output was off by
a tenth of its range near the seams, silently.
"""

from __future__ import annotations

import numpy as np
import pytest

torch = pytest.importorskip("torch")
F = torch.nn.functional

from types import SimpleNamespace  # noqa: E402

from mehs.errors import InputError  # noqa: E402


class CellNet(torch.nn.Module):
    """A 3×3 convolution plus the mean of each ``cell × cell`` block (functional ops only:
    no module ever sees the pooled map). Its grid is ``cell``."""

    def __init__(self, cell: int):
        super().__init__()
        self.cell = cell
        self.a = torch.nn.Conv2d(3, 4, 3, padding=1)
        self.b = torch.nn.Conv2d(3, 4, 1)

    def forward(self, x):
        h, w = x.shape[-2:]
        c = self.cell
        y = F.pad(self.b(x), (0, (-w) % c, 0, (-h) % c), mode="replicate")
        y = F.interpolate(F.avg_pool2d(torch.tanh(y), c), scale_factor=c, mode="nearest")
        return self.a(x) + y[..., :h, :w]


class AvgUNet(torch.nn.Module):
    """A U-Net of ``levels`` average poolings (no ``depth`` attribute): grid ``2**levels``;
    ``pad``: it pads itself to its grid (else it takes multiples of it only)."""

    def __init__(self, levels: int, ch: int = 4, bands: int = 4, pad: bool = False):
        super().__init__()
        self.levels, self.pad = levels, pad
        self.inc = torch.nn.Conv2d(3, ch, 3, padding=1)
        self.down = torch.nn.ModuleList(torch.nn.Conv2d(ch, ch, 3, padding=1)
                                        for _ in range(levels))
        self.up = torch.nn.ModuleList(torch.nn.Conv2d(ch, ch, 1) for _ in range(levels))
        self.out = torch.nn.Conv2d(ch, bands, 1)

    def forward(self, x):
        h, w = x.shape[-2:]
        if self.pad:
            m = 2 ** self.levels
            x = F.pad(x, (0, (-w) % m, 0, (-h) % m), mode="replicate")
        y, skips = torch.relu(self.inc(x)), []
        for d in self.down:
            skips.append(y)
            y = F.avg_pool2d(torch.tanh(d(y)), 2)
        for u, s in zip(self.up, reversed(skips)):
            y = F.interpolate(torch.tanh(u(y)), scale_factor=2, mode="nearest") + s
        return self.out(y)[..., :h, :w]


def _tiled_vs_whole(net, rgb, **opts):
    from mehs.ssr.tiling_torch import tiled_torch_call

    with torch.no_grad():
        whole = net(torch.from_numpy(rgb.transpose(2, 0, 1).copy())[None])[0]
    whole = whole.permute(1, 2, 0).numpy()
    model = SimpleNamespace(network=net, device="cpu", name="user", tiling=dict(
        bytes_per_pixel=1.0, blend=8, statistics="tile", **opts))
    tiled = tiled_torch_call(model, rgb)
    return tiled, whole, model


@pytest.mark.parametrize("cell", [16, 32, 24])
def test_a_network_pooling_through_functional_ops_is_tiled_on_its_grid(cell):
    torch.manual_seed(cell)
    net = CellNet(cell).eval()
    rng = np.random.default_rng(cell)
    rgb = rng.random((288, 384, 3), dtype=np.float32)
    tiled, whole, model = _tiled_vs_whole(net, rgb, max_bytes=150 * 150)
    assert model._tiling_last["summary"]["tiles"] >= 4
    assert model._tiling_probe["align"] % cell == 0
    np.testing.assert_allclose(tiled, whole, rtol=0, atol=1e-5 * np.abs(whole).max())


def test_a_user_unet_without_a_depth_attribute_is_tiled_on_its_grid():
    from mehs.ssr.tiling_probes import torch_align

    torch.manual_seed(0)
    net = AvgUNet(5).eval()
    assert torch_align(net) == 32
    rgb = np.random.default_rng(1).random((256, 448, 3), dtype=np.float32)
    tiled, whole, model = _tiled_vs_whole(net, rgb, max_bytes=224 * 224, margin=64)
    assert model._tiling_last["summary"]["tiles"] >= 2
    np.testing.assert_allclose(tiled, whole, rtol=0, atol=1e-5 * np.abs(whole).max())


def test_strides_are_read_from_exact_and_rounded_map_sizes():
    from mehs.ssr.tiling_grid import _area_stride, _axis_stride

    assert _axis_stride(192, 384, 128, 256) == 2
    assert _axis_stride(3, 384, 2, 256) == 128        # not 127 (which rounds to it too)
    assert _axis_stride(128, 384, 86, 256) == 3       # 256 padded to 258 before pooling
    assert _axis_stride(16, 384, 11, 256) == 24       # 256 padded to 264
    assert _axis_stride(384, 384, 256, 256) == 1      # full size
    assert _axis_stride(1, 384, 1, 256) is None       # a global statistic
    assert _axis_stride(48, 384, 48, 256) is None     # does not follow the input
    assert _axis_stride(768, 384, 512, 256) is None   # up-sampled
    assert _area_stride(384, (384, 256), 96, (192, 128)) == 16      # 16×16 windows
    assert _area_stride(2035, (384, 256), 28 * 19, (192, 128)) == 7  # 7×7, padded


class Decoy(torch.nn.Module):
    """Local, with shapes that look down-sampled but do not follow the input: a
    48×32 parameter, a global 1×1 pooling, and a 96×64 attention-like matrix."""

    def __init__(self):
        super().__init__()
        self.w = torch.nn.Parameter(torch.randn(48, 32))
        self.q = torch.nn.Parameter(torch.randn(96, 3))
        self.conv = torch.nn.Conv2d(3, 3, 3, padding=1)

    def forward(self, x):
        y = self.conv(x)
        gate = torch.sigmoid(F.adaptive_avg_pool2d(y, 1))
        mix = (self.w * 2.0).sum() + (self.q @ self.q[:64].T).mean()   # (48, 32), (96, 64)
        return y * gate + 1e-3 * mix


def test_shapes_that_do_not_follow_the_input_are_no_grid():
    from mehs.ssr.tiling_grid import torch_grid, torch_strides

    torch.manual_seed(0)
    assert torch_strides(Decoy().eval()) == set()
    assert torch_grid(Decoy().eval()) == 1


def test_strides_of_traced_modules_and_pixel_unshuffle():
    from mehs.ssr.tiling_grid import torch_strides

    torch.manual_seed(0)
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecationWarning)    # torch ≥ 2.9 on jit
        traced = torch.jit.trace(AvgUNet(4).eval(), torch.rand(1, 3, 64, 64))
    assert torch_strides(traced) == {2, 4, 8, 16}

    class Shuffle(torch.nn.Module):
        def __init__(self):
            super().__init__()
            self.conv = torch.nn.Conv2d(48, 48, 3, padding=1)

        def forward(self, x):
            return F.pixel_shuffle(self.conv(F.pixel_unshuffle(x, 4)), 4)

    assert torch_strides(Shuffle().eval()) == {4}


def test_the_measured_grid_agrees_with_what_mehs_networks_declare():
    from mehs.ssr.net import build_network
    from mehs.ssr.tiling_grid import torch_strides

    torch.manual_seed(0)
    net = build_network().eval()                       # three poolings of the FC-DenseNet
    depth = max(m.depth for m in net.modules() if isinstance(getattr(m, "depth", None), int))
    # (its rows run in strips of so many pixels: they follow the width inversely, and
    # are no stride of 3)
    assert torch_strides(net) == {2, 4, 8} and 2 ** depth == 8


def test_the_grid_probe_leaves_the_callers_random_state_alone():
    from mehs.ssr.tiling_grid import torch_grid

    net = CellNet(16).eval()
    torch.manual_seed(3)
    expected = torch.rand(4)
    torch.manual_seed(3)
    torch_grid(net)
    assert torch.equal(torch.rand(4), expected)


def test_the_grid_probe_fits_a_pixel_cap():
    from mehs.ssr.tiling_grid import torch_grid

    seen = []

    class Recorder(CellNet):
        def forward(self, x):
            seen.append(x.shape[-2] * x.shape[-1])
            return super().forward(x)

    assert torch_grid(Recorder(16).eval(), max_pixels=40_000) == 16
    assert max(seen) <= 40_000
    # not below 192×128: a network padding to a grid of 64 read 13 and 24 at 96×64
    seen.clear()
    assert torch_grid(Recorder(16).eval(), max_pixels=5_000) == 16
    assert max(seen) == 192 * 128


class BrightGate(torch.nn.Module):
    """A 3×3 convolution, plus a path 16 px wide open only where the input exceeds 2."""

    def __init__(self):
        super().__init__()
        self.near = torch.nn.Conv2d(3, 4, 3, padding=1)
        self.far = torch.nn.Conv2d(3, 4, 3, padding=16, dilation=16)

    def forward(self, x):
        return self.near(x) + self.far(torch.relu(x - 2.0))


@pytest.mark.parametrize("forward_mode", [False, True])
def test_the_field_probes_see_a_path_open_only_on_bright_pixels(forward_mode):
    # on inputs in [0, 1) the gate is shut and the field read 1 px: tiles of HDR radiance
    # with a 1-px margin lost the far path at their seams
    from mehs.ssr.tiling_probes import _forward_mode_margin, torch_receptive_radius

    torch.manual_seed(0)
    net = BrightGate().eval()
    if forward_mode:
        # the perturbed block is one grid cell (8×8 pixels of many brightnesses)
        assert _forward_mode_margin(net, 128, 8, "cpu")[0] == 16
    else:
        with torch.enable_grad():
            assert torch_receptive_radius(net, align=1) == 16
            assert torch_receptive_radius(net, align=8) == 16


class Aniso(torch.nn.Module):
    """Pools rows by 2 and columns by 16: its grid is 16."""

    def __init__(self):
        super().__init__()
        self.a = torch.nn.Conv2d(3, 4, 3, padding=1)
        self.b = torch.nn.Conv2d(3, 4, 1)

    def forward(self, x):
        h, w = x.shape[-2:]
        y = F.pad(self.b(x), (0, (-w) % 16, 0, (-h) % 2), mode="replicate")
        y = F.interpolate(F.avg_pool2d(torch.tanh(y), (2, 16)), scale_factor=(2, 16),
                          mode="nearest")
        return self.a(x) + y[..., :h, :w]


class UnfoldWindows(torch.nn.Module):
    """Self-attention in 16×16 windows written with unfold / fold: its grid is 16, and
    no map of it is ever (H/16, W/16)."""

    def __init__(self, ws: int = 16, c: int = 4):
        super().__init__()
        self.ws, self.c = ws, c
        self.inp = torch.nn.Conv2d(3, c, 3, padding=1)
        self.qkv = torch.nn.Linear(c, 3 * c)

    def forward(self, x):
        h, w = x.shape[-2:]
        ws, c = self.ws, self.c
        y = F.pad(self.inp(x), (0, (-w) % ws, 0, (-h) % ws))
        t = F.unfold(y, ws, stride=ws)
        n = t.shape[-1]
        q, k, v = self.qkv(t.view(c, ws * ws, n).permute(2, 1, 0)).chunk(3, -1)
        a = torch.softmax(q @ k.transpose(1, 2) / c ** 0.5, -1) @ v
        y = y + F.fold(a.permute(2, 1, 0).reshape(1, c * ws * ws, n), y.shape[-2:], ws, stride=ws)
        return y[..., :h, :w]


@pytest.mark.parametrize("make", [Aniso, UnfoldWindows])
def test_anisotropic_poolings_and_flattened_windows_set_the_grid(make):
    # both were tiled on a grid of 8: 6.1e-2 and 1.6e-2 of the range off, silently
    torch.manual_seed(0)
    net = make().eval()
    rgb = np.random.default_rng(0).random((256, 448, 3), dtype=np.float32)
    tiled, whole, model = _tiled_vs_whole(net, rgb, max_bytes=200 * 200)
    assert model._tiling_probe["align"] % 16 == 0
    assert model._tiling_last["summary"]["tiles"] >= 3
    np.testing.assert_allclose(tiled, whole, rtol=0, atol=1e-5 * np.abs(whole).max())


class BlockNorm(torch.nn.Module):
    """Statistics of 16×16 blocks through a view: (C, H/16, 16, W/16, 16), no two of the
    block axes adjacent."""

    def __init__(self):
        super().__init__()
        self.conv = torch.nn.Conv2d(3, 4, 3, padding=1)

    def forward(self, x):
        h, w = x.shape[-2:]
        y = F.pad(self.conv(x), (0, (-w) % 16, 0, (-h) % 16), mode="replicate")
        c, hh, ww = y.shape[1], y.shape[2] // 16, y.shape[3] // 16
        v = y.view(1, c, hh, 16, ww, 16)
        v = (v - v.mean((3, 5), keepdim=True)) / (v.std((3, 5), keepdim=True) + 1e-3)
        return v.view(1, c, hh * 16, ww * 16)[..., :h, :w]


def test_block_statistics_through_a_view_set_the_grid():
    # the probe paired adjacent axes only: grid 8, tiles 1e-1 of the range off
    from mehs.ssr.tiling_grid import torch_strides

    torch.manual_seed(0)
    net = BlockNorm().eval()
    assert torch_strides(net) == {16}
    rgb = np.random.default_rng(0).random((256, 448, 3), dtype=np.float32)
    tiled, whole, model = _tiled_vs_whole(net, rgb, max_bytes=170 * 170)
    assert model._tiling_last["summary"]["tiles"] >= 3
    np.testing.assert_allclose(tiled, whole, rtol=0, atol=1e-5 * np.abs(whole).max())
