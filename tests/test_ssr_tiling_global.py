"""Tiles of a network with channel attention equal the whole image with image-wide means (issue 16)."""

from types import SimpleNamespace

import warnings

import numpy as np
import pytest
from _checks import contrast_rgb

from mehs.errors import InputError
from mehs.ssr.tiling import TilingPlan, tile_starts

torch = pytest.importorskip("torch")

from mehs.ssr.net import ChannelAttention, build_network  # noqa: E402
from mehs.ssr.tiling_torch import tiled_torch_call  # noqa: E402
from mehs.ssr.tiling_global import owned_spans  # noqa: E402


def _attentive_net(seed=0, gain=20.0):
    """The paper's network (tiny preset) with its channel attention made strongly
    image-dependent, as training makes it (at initialisation the scales hardly move,
    and per-tile means would pass any test)."""
    torch.manual_seed(seed)
    net = build_network(arch="hdrssr", preset="tiny").eval()
    with torch.no_grad():
        for m in net.modules():
            if isinstance(m, ChannelAttention):
                m.squeeze.weight.mul_(gain)
                m.excite.weight.mul_(gain)
    return net


_rgb = contrast_rgb


def _run(net, rgb, **tiling):
    model = SimpleNamespace(network=net, device="cpu", name="hdrssr",
                            tiling=tiling or "off")
    return tiled_torch_call(model, rgb), model


@pytest.mark.parametrize("shape,tile", [((64, 300), (64, 128)),      # strips, a padded last one
                                        ((130, 170), (72, 88))])     # a grid, odd sizes
def test_image_means_make_tiles_equal_the_whole_image(shape, tile):
    net = _attentive_net()
    rgb = _rgb(*shape)
    whole, _ = _run(net, rgb)
    opts = dict(bytes_per_pixel=1.0, max_bytes=tile[0] * tile[1], blend=16)
    per_tile, m1 = _run(net, rgb, statistics="tile", **opts)
    image, m2 = _run(net, rgb, **opts)                  # the default: "auto"
    plan = m2._tiling_last["plan"]
    assert plan.tile is not None and m2._tiling_last["summary"]["tiles"] >= 3
    assert m2._tiling_last["statistics"] == "image"
    assert m1._tiling_last["statistics"] == "tile"
    scale = np.abs(whole).max()
    # each tile's own means: a clear difference (this is what image-wide means are for)
    assert np.abs(per_tile - whole).max() > 1e-4 * scale
    np.testing.assert_allclose(image, whole, rtol=0, atol=1e-5 * scale)


def test_image_means_from_the_environment(monkeypatch):
    net = _attentive_net(seed=1)
    rgb = _rgb(64, 300, seed=4)
    whole, _ = _run(net, rgb)
    monkeypatch.setenv("MEHS_TILE_STATISTICS", "tile")
    per_tile, m = _run(net, rgb, bytes_per_pixel=1.0, max_bytes=64 * 128)
    assert m._tiling_last["statistics"] == "tile"
    assert np.abs(per_tile - whole).max() > 1e-4 * np.abs(whole).max()
    monkeypatch.setenv("MEHS_TILE_STATISTICS", "image")
    image, m = _run(net, rgb, bytes_per_pixel=1.0, max_bytes=64 * 128)
    assert m._tiling_last["statistics"] == "image"
    np.testing.assert_allclose(image, whole, rtol=0, atol=1e-5 * np.abs(whole).max())
    monkeypatch.setenv("MEHS_TILE_STATISTICS", "exact")
    with pytest.raises(InputError, match="statistics must be one of"):
        _run(net, rgb, bytes_per_pixel=1.0, max_bytes=64 * 128)


@pytest.mark.parametrize("margin,blend", [(9, 2), (41, 2), (57, 3)])
def test_a_margin_off_the_grid_still_gets_image_wide_means(margin, blend):
    # a user's margin and blend that leave no grid line a margin inside both tiles of an
    # overlap: the margin goes up to the grid instead of the default mode failing
    net = _attentive_net(seed=2)
    rgb = _rgb(64, 300, seed=5)
    whole, _ = _run(net, rgb)
    out, m = _run(net, rgb, bytes_per_pixel=1.0, max_bytes=64 * 160, margin=margin,
                  blend=blend)
    plan = m._tiling_last["plan"]
    assert plan.margin % plan.align == 0 and plan.margin >= margin
    assert m._tiling_last["statistics"] == "image" and m._tiling_last["summary"]["tiles"] >= 2
    np.testing.assert_allclose(out, whole, rtol=0, atol=1e-5 * np.abs(whole).max())
    # each tile's own means keep the margin as given
    _, m = _run(net, rgb, bytes_per_pixel=1.0, max_bytes=64 * 160, margin=margin,
                blend=blend, statistics="tile")
    assert m._tiling_last["plan"].margin == margin


def test_owned_spans_partition_the_axis_inside_the_exact_zones():
    for n, tile, margin, blend, align in [(300, 128, 16, 16, 8), (1000, 160, 30, 8, 8),
                                          (257, 96, 9, 4, 4), (130, 72, 16, 16, 8)]:
        plan = TilingPlan(tile, margin, blend, align)
        spans = owned_spans(n, tile, plan)
        starts = tile_starts(n, tile, plan.overlap, align)
        assert list(spans) == starts
        bounds = [spans[s][:2] for s in starts]
        assert bounds[0][0] == 0 and bounds[-1][1] == n and spans[starts[-1]][2]
        for (a, b), (c, d) in zip(bounds, bounds[1:]):
            assert b == c and a < b and b % align == 0
        for k, s in enumerate(starts):
            lo, hi, last = spans[s]
            end = n if last else s + tile
            assert k == 0 or lo >= s + margin           # a margin inside the tile
            assert last or hi <= end - margin


def test_owned_spans_need_room_on_the_grid():
    with pytest.raises(InputError, match="blend of at least 8"):
        owned_spans(300, 64, TilingPlan(64, 4, 0, 8))      # overlap 8: only pixel 60


def test_networks_without_poolings_or_with_other_global_operations():
    # local: plain tiles are exact already, and image statistics change nothing
    from mehs.ssr.tiling_probes import GLOBAL_MARGIN

    torch.manual_seed(2)
    net = build_network(arch="galliani", preset="tiny").eval()     # dropout, no attention
    rgb = _rgb(64, 300)
    plain, _ = _run(net, rgb, bytes_per_pixel=1.0, max_bytes=64 * 128)
    image, _ = _run(net, rgb, bytes_per_pixel=1.0, max_bytes=64 * 128, statistics="image")
    np.testing.assert_array_equal(plain, image)
    # a global operation other than a pooling: the margin probe reached everywhere
    model = SimpleNamespace(network=_attentive_net(), device="cpu", name="global",
                            tiling=dict(bytes_per_pixel=1.0, max_bytes=64 * 200,
                                        statistics="image"),
                            _tiling_probe={"margin": GLOBAL_MARGIN, "align": 8})
    with pytest.raises(InputError, match="not statistics tiles can assemble"):
        tiled_torch_call(model, _rgb(64, 400))
    # by default such a network keeps each tile's own statistics, and says so (session 26)
    model.tiling = dict(bytes_per_pixel=1.0, max_bytes=64 * 200)
    with pytest.warns(RuntimeWarning, match="tiles use their own statistics"):
        tiled_torch_call(model, _rgb(64, 400))
    assert model._tiling_last["statistics"] == "tile"
    # unless that was asked for
    model.tiling = dict(bytes_per_pixel=1.0, max_bytes=64 * 200, statistics="tile")
    with warnings.catch_warnings():
        warnings.simplefilter("error", RuntimeWarning)
        tiled_torch_call(model, _rgb(64, 400))


def test_collecting_run_stops_at_the_last_pooling():
    # no tile of the collecting run goes through the basis branches after the last
    # attention layer (a forward on a small crop shows where that is); the final run's
    # tiles all do
    net = _attentive_net(seed=2)
    done = []
    net.register_forward_hook(lambda mod, inp, out: done.append(inp[0].shape[-2] * inp[0].shape[-1]))
    rgb = _rgb(64, 300, seed=6)
    # (margin and grid given: no probe runs a forward of its own)
    _, m = _run(net, rgb, bytes_per_pixel=1.0, max_bytes=64 * 128, statistics="image",
                margin=16, align=8)
    n, runs = m._tiling_last["summary"]["tiles"], m._tiling_last["image_runs"]
    assert n >= 3 and runs >= 2 and m._tiling_last["image_means_change"] <= 1e-5
    plan = m._tiling_last["plan"]
    tile_px = min(plan.tile, 64) * min(plan.width, 300)
    # one completed forward on the crop, far smaller than a tile, then the final runs'
    assert len(done) == 1 + n * (runs - 1)
    assert done[0] <= tile_px // 4 and min(done[1:]) > tile_px // 2


class _SharedAttention(torch.nn.Module):
    """One attention layer called twice per forward: each call pools its own input."""

    def __init__(self):
        super().__init__()
        nn = torch.nn
        self.a, self.b = nn.Conv2d(3, 8, 3, padding=1), nn.Conv2d(8, 8, 3, padding=1)
        self.out = nn.Conv2d(8, 5, 3, padding=1)
        self.ca = ChannelAttention(8, 2)
        with torch.no_grad():
            self.ca.squeeze.weight.mul_(20.0)
            self.ca.excite.weight.mul_(20.0)

    def forward(self, x):
        x = self.ca(torch.relu(self.a(x)))
        return self.out(self.ca(torch.relu(self.b(x))))


def test_a_layer_called_twice_pools_each_call_image_wide():
    torch.manual_seed(7)
    net = _SharedAttention().eval()
    rgb = _rgb(48, 200, seed=8)
    whole, _ = _run(net, rgb)
    image, m = _run(net, rgb, bytes_per_pixel=1.0, max_bytes=48 * 64, statistics="image")
    assert m._tiling_last["summary"]["tiles"] >= 3
    np.testing.assert_allclose(image, whole, rtol=0, atol=1e-5 * np.abs(whole).max())
