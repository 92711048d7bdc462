"""Lean SSR network inference (issue 16): row strips, a cheap max-pool, and collecting runs
that never run the head. Each must give the numbers of the plain training graph."""

import warnings

import numpy as np
import pytest
from _checks import contrast_rgb, peak_live_bytes

torch = pytest.importorskip("torch")
torch.set_num_threads(1)

import torch.nn.functional as F  # noqa: E402

from mehs.ssr.net import ChannelAttention, build_network  # noqa: E402
from mehs.ssr.net.layers import MaxPool2x2  # noqa: E402
from mehs.ssr.tiling_torch import tiled_torch_call  # noqa: E402


def _model(net, name="toy", **tiling):
    """The attributes :func:`tiled_torch_call` reads of a torch SSR model."""
    from types import SimpleNamespace

    return SimpleNamespace(network=net, device="cpu", name=name, tiling=tiling or "off")


#: A budget in which ``_WideAttention``'s 128² field probe fills and its 256² one does not fit.
WIDE_TILING = dict(bytes_per_pixel=1.0, max_bytes=40 * 320, statistics="image", blend=8)


def _assert_strips_match_graph(net, rgb, tol=1e-6):
    """The network's inference (row strips, no autograd) equals its autograd graph's
    output (which never runs in strips), to ``tol`` relative and of the largest value."""
    with torch.no_grad():
        lean = net(rgb)
    plain = net(rgb.clone().requires_grad_()).detach()
    torch.testing.assert_close(lean, plain, rtol=tol, atol=tol * float(plain.abs().max()))


def _chunked(net, pixels):
    for m in net.modules():
        if isinstance(getattr(m, "chunk_pixels", None), int):
            m.chunk_pixels = pixels


@pytest.mark.parametrize("arch", ["hdrssr", "mikamoto", "galliani"])
@pytest.mark.parametrize("n", [1, 2])
def test_row_strips_give_the_training_graphs_numbers(arch, n):
    # strips of a few rows, so that every dense layer, transition and head runs in many
    # of them, with the convolutions' context rows at both image edges and between strips
    torch.manual_seed(3)
    net = build_network(arch=arch, preset="tiny").eval()
    rgb = torch.rand(n, 3, 45, 37) * 20
    _chunked(net, 150)
    # same sums per pixel; only the head's 1×1 convolutions may round differently per shape
    _assert_strips_match_graph(net, rgb)


def _peak_live_bytes(net, x):
    with torch.no_grad():
        return peak_live_bytes(lambda: net(x))


def test_inference_holds_about_two_full_resolution_maps_not_five():
    # the small paper network's widest full-resolution map is the last block's 64
    # channels and its output has 31: the head and dense layers used to hold ~194
    # channels' worth of full-resolution maps at once, the strips ~105
    torch.manual_seed(0)
    net = build_network(arch="hdrssr", preset="small").eval()
    side = 512
    _chunked(net, 4096)                # strips far smaller than the image, as on a large one
    peak = _peak_live_bytes(net, torch.rand(1, 3, side, side))
    per_pixel_channels = peak / (side * side * 4)
    assert per_pixel_channels < 115, per_pixel_channels


def test_max_pool_is_torchs_max_pool():
    torch.manual_seed(0)
    x = torch.randn(2, 5, 9, 12)
    x[0, 0, 0, 0], x[1, 2, 3, 4], x[0, 3, 8, 11] = float("nan"), float("inf"), -float("inf")
    pool = MaxPool2x2()
    with torch.no_grad():
        for t in (x, x[..., :7, :11], x[..., 1:, :]):       # odd sizes floor, views work
            got, want = pool(t), F.max_pool2d(t, 2)
            assert got.shape == want.shape
            assert torch.equal(torch.isnan(got), torch.isnan(want))
            assert torch.equal(got.nan_to_num(), want.nan_to_num())
    y = pool(x.clone().requires_grad_())                   # autograd: the stock operator
    assert y.requires_grad


class _SizeDependent(torch.nn.Module):
    """A second attention layer that only large inputs pass through: a small crop's
    forward shows the first as the last pooling."""

    def __init__(self):
        super().__init__()
        nn = torch.nn
        self.a, self.b = nn.Conv2d(3, 8, 3, padding=1), nn.Conv2d(8, 8, 3, padding=1)
        self.out = nn.Conv2d(8, 5, 3, padding=1)
        self.ca1, self.ca2 = ChannelAttention(8, 2), ChannelAttention(8, 2)
        with torch.no_grad():
            for ca in (self.ca1, self.ca2):
                ca.squeeze.weight.mul_(20.0)
                ca.excite.weight.mul_(20.0)

    def forward(self, x):
        x = self.ca1(torch.relu(self.a(x)))
        x = torch.relu(self.b(x))
        if x.shape[-2] * x.shape[-1] > 40 * 40:
            x = self.ca2(x)
        return self.out(x)


def test_a_crop_that_pools_differently_costs_a_run_not_the_result():
    torch.manual_seed(4)
    net = _SizeDependent().eval()
    rgb = contrast_rgb(48, 400, seed=2)

    def run(**tiling):
        model = _model(net, **tiling)
        return tiled_torch_call(model, rgb), model

    whole, _ = run()
    with warnings.catch_warnings():
        # its second attention layer runs on tiles over 1600 px only: the check of the
        # tiles on a probe image (session 26) may take it for a network whose tiles differ
        warnings.simplefilter("ignore", RuntimeWarning)
        image, m = run(bytes_per_pixel=1.0, max_bytes=48 * 136, statistics="image",
                       margin=8, align=8)
    assert m._tiling_last["summary"]["tiles"] >= 3
    # the collecting run stopped after ca1, so ca2's means came one run later
    assert m._tiling_last["image_runs"] >= 3
    assert m._tiling_last["image_means_change"] <= 1e-5
    np.testing.assert_allclose(image, whole, rtol=0, atol=1e-5 * np.abs(whole).max())


class _WideField(torch.nn.Module):
    """Twenty 3×3 convolutions: a 20-pixel receptive radius, wider than a 32² probe."""

    def __init__(self):
        super().__init__()
        self.convs = torch.nn.ModuleList(torch.nn.Conv2d(3, 3, 3, padding=1) for _ in range(20))

    def forward(self, x):
        for c in self.convs:
            x = torch.tanh(c(x))
        return x


def _pairs(sizes):
    # every probe runs on two inputs (uniform, and HDR brightness: session 26)
    assert sizes[::2] == sizes[1::2], sizes
    return sizes[::2]


def test_receptive_field_probe_grows_only_within_the_memory_budget():
    # the full-size paper network's field is wider than 256 px: its autograd probes grew
    # to 512² and held 9 GB under a 2 GB cap before they gave up
    from mehs.ssr.tiling_probes import FieldWiderThanBudget, torch_receptive_radius

    torch.manual_seed(0)
    net = _WideField()
    sizes = []
    net.register_forward_pre_hook(lambda mod, inp: sizes.append(inp[0].shape[-1]))
    assert torch_receptive_radius(net, probe=32, max_probe=128) == 20
    assert _pairs(sizes) == [32, 64]
    sizes.clear()
    # the 64² gradient probe would not fit 1 MiB; a forward-mode one (a third of its
    # memory, measured on the 32² size first) does, and finds the same field
    assert torch_receptive_radius(net, probe=32, max_probe=128, max_bytes=1 << 20) == 20
    assert _pairs(sizes) == [32, 32, 64]
    sizes.clear()
    with pytest.raises(FieldWiderThanBudget) as e:
        torch_receptive_radius(net, probe=32, max_probe=128, max_bytes=256 << 10)
    assert _pairs(sizes) == [32, 32]       # neither 64² probe would have fitted 256 KiB
    assert e.value.lower_bound == 16 and e.value.probe == 32    # not a global operation
    sizes.clear()
    assert torch_receptive_radius(net, probe=32, max_probe=128, max_bytes=1 << 30) == 20
    assert _pairs(sizes) == [32, 64]


# -- what the strips must not change (an independent review's findings) ----------------

def test_strips_keep_forward_hooks_and_subclassed_attention():
    from mehs.ssr.net.layers import DenseLayer

    class Shifted(ChannelAttention):
        def forward(self, x):
            return x + super().forward(x)

    torch.manual_seed(5)
    net = build_network(arch="hdrssr", preset="tiny").eval()
    for m in list(net.modules()):
        if isinstance(m, DenseLayer) and isinstance(m[-1], ChannelAttention):
            old = m[-1]
            m[-1] = Shifted(old.squeeze.in_channels, 4)
            m[-1].load_state_dict(old.state_dict())
    _chunked(net, 150)
    rgb = torch.rand(1, 3, 40, 36) * 5
    _assert_strips_match_graph(net, rgb)
    calls = []
    layers = [m for m in net.modules() if isinstance(m, DenseLayer)]
    for m in layers:
        m.register_forward_hook(lambda *a: calls.append(1))
    with torch.no_grad():
        net(rgb)
    assert len(calls) == len(layers)


def test_batch_norm_without_running_statistics_is_not_split_into_strips():
    torch.manual_seed(6)
    net = build_network(arch="galliani", preset="tiny").eval()
    for m in net.modules():
        if isinstance(m, torch.nn.BatchNorm2d):
            m.track_running_stats = False      # normalises with the map's own statistics
            m.running_mean = m.running_var = None
    _chunked(net, 150)
    rgb = torch.rand(1, 3, 40, 36) * 5
    _assert_strips_match_graph(net, rgb, tol=1e-5)


class _WideAttention(torch.nn.Module):
    """A 70-pixel receptive radius (70 3×3 convolutions; ``layers × dilation`` in general)
    and one channel attention."""

    def __init__(self, layers: int = 70, dilation: int = 1):
        super().__init__()
        self.convs = torch.nn.ModuleList(
            torch.nn.Conv2d(3, 3, 3, padding=dilation, dilation=dilation) for _ in range(layers))
        self.ca = ChannelAttention(3, 1)
        self.out = torch.nn.Conv2d(3, 4, 1)

    def forward(self, x):
        for c in self.convs:
            x = torch.tanh(c(x))
        return self.out(self.ca(x))


def test_a_field_wider_than_the_budget_allows_to_probe_is_not_a_global_operation():
    # a 128² autograd probe fills; the budget forbids the 256² one: before, that answer
    # was the global operations' margin, so image-wide means were refused (and cached)
    torch.manual_seed(8)
    model = _model(_WideAttention().eval(), "wide", **WIDE_TILING)
    rgb = contrast_rgb(40, 480, seed=3)
    with pytest.warns(RuntimeWarning, match="receptive field is wider than a 128-pixel probe"):
        tiled_torch_call(model, rgb)
    assert model._tiling_probe["margin"] >= 64 and model._tiling_probe["margin_bound"]
    assert model._tiling_last["statistics"] == "image"
    assert model._tiling_last["summary"]["tiles"] >= 2


class _MeansDependent(torch.nn.Module):
    """A pooling before the last that runs only once image-wide means are handed out:
    no collecting run sees it, so image-wide means cannot be assembled for it."""

    def __init__(self):
        super().__init__()
        self.a = torch.nn.Conv2d(3, 4, 3, padding=1)
        self.ca_mid, self.ca_last = ChannelAttention(4, 2), ChannelAttention(4, 2)
        self.out = torch.nn.Conv2d(4, 3, 1)

    def forward(self, x):
        from mehs.ssr.net import pooling

        x = torch.relu(self.a(x))
        ctx = pooling._ACTIVE.get()
        if ctx is not None and ctx._means is not None:
            x = self.ca_mid(x)
        return self.out(self.ca_last(x))


def test_a_pooling_missing_before_where_collecting_stopped_is_refused():
    from mehs.errors import InputError

    torch.manual_seed(9)
    model = _model(_MeansDependent().eval(), bytes_per_pixel=1.0, max_bytes=40 * 96,
                   statistics="image", margin=8, align=8)
    with pytest.raises(InputError, match="did not see"):
        tiled_torch_call(model, contrast_rgb(40, 300, seed=4))


def test_a_lower_bound_margin_is_probed_again_by_the_next_call(monkeypatch):
    import mehs.ssr.tiling_torch as tiling

    torch.manual_seed(10)
    model = _model(_WideAttention().eval(), "wide", **WIDE_TILING)
    rgb = contrast_rgb(40, 480, seed=3)
    with pytest.warns(RuntimeWarning, match="receptive field is wider"):
        tiled_torch_call(model, rgb)
    assert model._tiling_probe["margin_bound"]
    # a budget that holds the 256² probe: measured now, and no longer a bound
    real = tiling.torch_receptive_radius
    seen = []

    def roomy(*a, **k):
        seen.append(k.get("max_bytes"))
        k["max_bytes"] = 1 << 34
        return real(*a, **k)

    monkeypatch.setattr(tiling, "torch_receptive_radius", roomy)
    tiled_torch_call(model, rgb)
    assert seen and model._tiling_probe["margin"] == 72     # 70 px, on the 8-px grid
    assert not model._tiling_probe.get("margin_bound")


def test_hooks_that_replace_the_head_or_an_up_block_output_are_honoured():
    from mehs.ssr.net.layers import DenseBlock

    torch.manual_seed(11)
    net = build_network(arch="hdrssr", preset="tiny").eval()
    _chunked(net, 150)
    rgb = torch.rand(1, 3, 40, 36) * 5
    net.sigmoid_branch.register_forward_hook(lambda m, i, y: y * 0.5)
    up = net.features.up_blocks[-1]
    assert isinstance(up, DenseBlock)
    up.register_forward_hook(lambda m, i, y: y + 0.25)
    _assert_strips_match_graph(net, rgb)
