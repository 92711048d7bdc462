"""Tiled network inference equals whole-image inference for local networks (issue 16)."""

from types import SimpleNamespace

import numpy as np
import pytest
from _checks import MALLINFO2, has_mallinfo2

from mehs.errors import InputError
from mehs.ssr.tiling import TilingPlan, plan_tiles, predict_tiled, tile_starts

torch = pytest.importorskip("torch")

from mehs.ssr.tiling import allocator_overhead, torch_memory_probe  # noqa: E402
nn = torch.nn


def _tile_budget(net, side):
    """The memory budget within which a ``side × side`` tile just fits (the library's model)."""
    m = torch_memory_probe(net)
    n = side * side
    return int(allocator_overhead(n) * (m["fixed_bytes"] + m["bytes_per_pixel"] * n))


class LocalUNet(nn.Module):
    """A tiny fully convolutional U-Net (2 poolings, no global operation): tile-invariant."""

    depth = 2

    def __init__(self, bands: int = 5):
        super().__init__()
        self.a = nn.Conv2d(3, 6, 3, padding=1)
        self.b = nn.Conv2d(6, 6, 3, padding=1)
        self.c = nn.Conv2d(6, 6, 3, padding=1)
        self.up = nn.ConvTranspose2d(6, 6, 3, stride=2, padding=1, output_padding=1)
        self.out = nn.Conv2d(12, bands, 3, padding=1)

    def forward(self, x):
        h, w = x.shape[-2:]
        x = nn.functional.pad(x, (0, (-w) % 4, 0, (-h) % 4), mode="replicate")
        s = torch.relu(self.a(x))
        y = torch.relu(self.b(nn.functional.max_pool2d(s, 2)))
        y = torch.relu(self.c(nn.functional.max_pool2d(y, 2)))
        y = self.up(nn.functional.interpolate(y, scale_factor=2.0, mode="nearest"))
        y = nn.functional.interpolate(y, size=s.shape[-2:], mode="nearest")
        return self.out(torch.cat([s, y], 1))[..., :h, :w]


def _rgb(h, w, seed=0):
    return np.random.default_rng(seed).gamma(1.0, 1.0, (h, w, 3)).astype(np.float32)


def _model(net, **tiling):
    torch.manual_seed(0)
    return SimpleNamespace(network=net.eval(), device="cpu", tiling=tiling or "off")


@pytest.mark.parametrize("shape", [(150, 230), (96, 128)])
def test_torch_tiles_equal_whole_image(shape):
    from mehs.ssr.tiling_torch import tiled_torch_call

    torch.manual_seed(1)
    net = LocalUNet()
    rgb = _rgb(*shape)
    whole = tiled_torch_call(_model(net), rgb)
    # a budget of a 72×72 tile forces several tiles in both directions
    budget = _tile_budget(net, 72)
    m = _model(net, max_bytes=budget)
    tiled = tiled_torch_call(m, rgb)
    probe = m._tiling_probe
    assert probe["align"] == 8 and 5 <= probe["margin"] <= 40
    plan = m._tiling_last["plan"]
    assert plan.tile is not None and (plan.tile < shape[0] or plan.width < shape[1])
    np.testing.assert_allclose(tiled, whole, rtol=1e-5, atol=1e-5 * np.abs(whole).max())


def test_mehs_network_tiles_equal_whole_image_when_local():
    # the real FC-DenseNet architecture (3 poolings, dense skips, replicate padding);
    # its channel attention is made local (constant scale) so exact equality is expected
    from mehs.ssr.net import build_network
    from mehs.ssr.tiling_torch import tiled_torch_call

    torch.manual_seed(2)
    net = build_network(variant="fcdensenet", first_channels=8, down_layers=(1, 1, 1),
                        bottleneck_layers=1, growth=4)
    for mod in net.modules():
        if type(mod).__name__ == "ChannelAttention":
            nn.init.zeros_(mod.excite.weight)
            nn.init.zeros_(mod.excite.bias)
    rgb = _rgb(120, 176, seed=3)
    whole = tiled_torch_call(_model(net), rgb)
    budget = _tile_budget(net, 112)
    m = _model(net, max_bytes=budget)
    tiled = tiled_torch_call(m, rgb)
    assert m._tiling_probe["align"] == 8
    plan = m._tiling_last["plan"]
    assert plan.tile is not None and (plan.tile < 120 or plan.width < 176)
    np.testing.assert_allclose(tiled, whole, rtol=1e-5, atol=1e-5 * np.abs(whole).max())


def test_onnx_tiles_equal_whole_image(tmp_path):
    pytest.importorskip("onnxruntime")
    pytest.importorskip("onnx")
    from mehs.ssr.models import OnnxModel

    torch.manual_seed(4)
    net = LocalUNet(bands=31).eval()
    path = tmp_path / "local.onnx"
    torch.onnx.export(net, (torch.rand(1, 3, 64, 64),), str(path), dynamo=False,
                      input_names=["rgb"], output_names=["spectra"],
                      dynamic_axes={"rgb": {2: "h", 3: "w"}, "spectra": {2: "h", 3: "w"}})
    model = OnnxModel(path)
    rgb = _rgb(300, 260, seed=5)
    model.tiling = "off"
    whole = model.predict(rgb)
    calls = []
    whole_fn = model._predict_whole

    def spy(x):
        calls.append(x.shape[:2])
        return whole_fn(x)

    model._predict_whole = spy
    model.tiling = {"bytes_per_pixel": 1000.0, "max_bytes": 1000 * 224 ** 2}
    tiled = model.predict(rgb)
    # measured by finite differences on the graph (session 26; a fixed 64 before): the
    # reach of a cut, within the field autograd finds on the torch network
    from mehs.ssr.tiling_probes import torch_receptive_radius

    with torch.enable_grad():
        field = torch_receptive_radius(net, align=8)
    assert model._tiling_probe["align"] == 8
    assert 0 < model._tiling_probe["margin"] <= field
    assert len(calls) >= 4 and max(h * w for h, w in calls) <= 224 ** 2
    np.testing.assert_allclose(tiled, whole, rtol=1e-5, atol=1e-5 * np.abs(whole).max())


def test_image_within_budget_runs_whole():
    calls = []

    def fn(x):
        calls.append(x.shape)
        return np.repeat(x[:, :, :1], 4, axis=2)

    rgb = _rgb(40, 50)
    plan = plan_tiles((40, 50), 100.0, margin=4, max_bytes=40 * 50 * 100)
    assert plan.tile is None
    out = predict_tiled(fn, rgb, plan)
    assert calls == [(40, 50, 3)]
    np.testing.assert_array_equal(out, np.repeat(rgb[:, :, :1], 4, axis=2))


def test_tile_grid_covers_axis_on_the_pooling_grid():
    for n, tile, overlap, align in [(1000, 256, 80, 32), (257, 64, 24, 8), (64, 64, 8, 8)]:
        starts = tile_starts(n, tile, overlap, align)
        assert all(s % align == 0 for s in starts)
        assert starts[-1] + tile >= n and starts[-1] < n
        for a, b in zip(starts, starts[1:]):
            assert b - a >= align and a + tile - b >= overlap   # neighbours share the overlap


def test_per_pixel_function_is_reproduced_exactly_by_the_blend():
    # weights sum to the blend's normaliser: a per-pixel map comes back bit-for-bit close
    rgb = _rgb(97, 131)
    plan = TilingPlan(tile=48, margin=4, blend=8, align=8)
    out = predict_tiled(lambda x: x * np.float32(2), rgb, plan)
    np.testing.assert_allclose(out, rgb * 2, rtol=1e-6)


def test_budget_too_small_is_a_clear_error():
    with pytest.raises(InputError, match="budget"):
        plan_tiles((2048, 1024), 4000.0, margin=60, max_bytes=10 * 2**20)


def test_small_images_and_roomy_budgets_skip_the_probes():
    from mehs.ssr.tiling import tiled_network_call

    called = []
    probes = {k: (lambda k=k: called.append(k) or 100.0)
              for k in ("bytes_per_pixel", "margin", "align")}
    model = SimpleNamespace(tiling="auto")
    fn = lambda x: x[:, :, :2]                                         # noqa: E731
    tiled_network_call(model, fn, _rgb(200, 300), probes)              # ≤ 256²: no probe at all
    assert called == []
    model.tiling = {"max_bytes": 10**9}
    tiled_network_call(model, fn, _rgb(300, 400), probes)              # fits: memory probe only
    assert called == ["bytes_per_pixel"]


def test_global_operation_gets_the_fallback_margin():
    from mehs.ssr.tiling import GLOBAL_MARGIN, torch_receptive_radius

    class GlobalNet(nn.Module):      # every output sees every input pixel
        def __init__(self):
            super().__init__()
            self.c = nn.Conv2d(3, 4, 1)

        def forward(self, x):
            y = self.c(x)
            return y + y.mean(dim=(2, 3), keepdim=True)

    assert torch_receptive_radius(GlobalNet(), probe=32, max_probe=64) == GLOBAL_MARGIN
    torch.manual_seed(0)
    assert 5 <= torch_receptive_radius(LocalUNet(), probe=64) <= 40


def test_tile_shape_minimises_recomputed_pixels():
    from mehs.ssr.tiling import _covered

    # 2048×1024 at ~0.5 M pixels per tile: the square is one of the candidates
    plan = plan_tiles((1024, 2048), 3000.0, margin=55, max_bytes=int(3000 * 523_000))
    assert plan.tile * plan.width * 3000.0 <= 3000 * 523_000
    cost = _covered(1024, plan.tile, plan.overlap, 8) * _covered(2048, plan.width, plan.overlap, 8)
    side = int((523_000) ** 0.5) // 8 * 8
    square = _covered(1024, side, plan.overlap, 8) * _covered(2048, side, plan.overlap, 8)
    assert cost <= square and cost < 1.3 * 1024 * 2048
    # blending with a non-square plan still reproduces a per-pixel map
    rgb = _rgb(97, 131)
    out = predict_tiled(lambda x: x + np.float32(1), rgb, TilingPlan(48, 4, 8, 8, tile_w=80))
    np.testing.assert_allclose(out, rgb + 1, rtol=1e-6)


def test_awan_tiles_bound_its_quadratic_attention(monkeypatch):
    # AWAN's non-local block attends over each quarter of its input: memory grows with the
    # square of the tile, which the per-pixel probe cannot see (a 2048×1024 image at once
    # asks ~1 TiB and the OOM killer ends the process). The network's own cap sets the tile.
    pytest.importorskip("torch")
    from mehs.ssr.net.zoo import build_network
    from mehs.ssr.tiling import plan_tiles, torch_bytes_per_pixel

    net = build_network(arch="awan", preset="tiny")
    budget = 256 << 20
    cap = net.max_tile_pixels(budget)
    quarter = cap / 4
    assert 3 * 4 * quarter ** 2 <= 1.01 * budget          # the affinity matrices fit
    bpp = max(torch_bytes_per_pixel(net, probe=32), budget / cap)
    plan = plan_tiles((1024, 2048), bpp, margin=net.TILING_MARGIN, max_bytes=budget)
    assert plan.tile is not None and plan.tile * plan.width <= cap


@pytest.mark.parametrize("make", ["local_unet", "fcdensenet"])
def test_margin_covers_every_phase_of_the_pooling_grid(make):
    # behind a pooling the receptive field depends on the pixel's phase on the grid;
    # the aligned margin must cover the worst phase at a tile's leading and trailing edge
    from mehs.ssr.net.pooling import detached_statistics
    from mehs.ssr.tiling_probes import torch_align, torch_receptive_radius

    torch.manual_seed(5)
    if make == "local_unet":
        net = LocalUNet().eval()
    else:
        from mehs.ssr.net import build_network
        # with these sizes a pixel at phase 1 reaches 23 px right, its phase-0 neighbour 20:
        # the former margin (phase-0 radius + 1 = 21) left the trailing edge inexact
        net = build_network(variant="fcdensenet", first_channels=8, down_layers=(2, 1),
                            bottleneck_layers=2, growth=4).eval()
    a = torch_align(net)
    m = torch_receptive_radius(net, probe=128, align=a)
    c = 64
    x = torch.rand(a, 3, 128, 128, requires_grad=True)
    with detached_statistics():                # the attention's mean is global
        sum(net(x)[p, :, c + p, c + p].sum() for p in range(a)).backward()
    for p in range(a):
        g = x.grad[p].abs().sum(0).numpy()
        ys, xs = np.nonzero(g > 0)
        left = c + p - min(ys.min(), xs.min())
        right = max(ys.max(), xs.max()) - (c + p)
        first = m + (p - m) % a                     # first weighted index with phase p
        last_d = m + (-1 - p - m) % a               # nearest distance to a trailing edge
        assert left <= first and right <= last_d, (p, left, right, m)


# ------------------------------------------------------------- the planner (fake memory)
def _brute_force(shape, bpp, margin, blend, align, max_bytes, fixed=0.0, out=0.0):
    """Fewest computed pixels (then fewest tiles) over every aligned tile shape that fits."""
    from mehs.ssr.tiling import _covered

    h, w = shape
    ov = 2 * margin + blend
    smallest = -(-(ov + align) // align) * align
    best = None
    for th in range(smallest, max(-(-h // align) * align, smallest) + 1, align):
        for tw in range(smallest, max(-(-w // align) * align, smallest) + 1, align):
            if fixed + bpp * min(th, h) * min(tw, w) + out > max_bytes:
                continue
            n = len(tile_starts(h, th, ov, align)) * len(tile_starts(w, tw, ov, align))
            c = (_covered(h, th, ov, align) * _covered(w, tw, ov, align), n)
            best = c if best is None or c < best else best
    return best


@pytest.mark.parametrize("shape,margin,blend,align,budget_px", [
    ((1024, 2048), 56, 16, 8, 830_000),      # the issue's case: three full-height strips
    ((2048, 2048), 56, 16, 8, 1_200_000),    # square image: blocks beat strips
    ((300, 1000), 20, 8, 8, 60_000),         # strips along the short side
    ((257, 131), 9, 4, 4, 9_000),            # odd sizes, a finer grid
    ((500, 500), 30, 0, 16, 90_000),
    ((64, 300), 32, 16, 8, 8_192),           # shorter than the smallest tile: one row
    ((1000, 64), 32, 16, 8, 6_400),          # narrower than it: one column
    ((300, 260), 64, 16, 32, 50_176),        # a full-width strip fits, its aligned width not
])
def test_plan_computes_the_fewest_pixels_within_the_budget(shape, margin, blend, align,
                                                           budget_px):
    from mehs.ssr.tiling import plan_summary

    bpp, fixed, out = 1000.0, 2.5e6, 0.4e9 * shape[0] * shape[1] / (1024 * 2048)
    budget = fixed + out + bpp * budget_px + 0.5     # off the aligned boundaries
    plan = plan_tiles(shape, bpp, margin=margin, blend=blend, align=align, max_bytes=budget,
                      fixed_bytes=fixed, out_bytes=out)
    s = plan_summary(shape, plan)
    assert plan.tile % align == 0 and plan.width % align == 0
    assert fixed + bpp * s["tile"][0] * s["tile"][1] + out <= budget        # the tile fits
    computed, tiles = _brute_force(shape, bpp, margin, blend, align, budget, fixed, out)
    assert round(s["computed"] * shape[0] * shape[1]) == computed and s["tiles"] == tiles


def test_plan_for_the_issue_image_is_three_strips():
    # 2048×1024, margin 56 (small hdrssr), ~0.83 M pixels a tile: full-height strips
    # recompute 2 overlaps of 128 px (1.125×); 2×2 blocks would recompute 1.19×
    from mehs.ssr.tiling import plan_summary

    plan = plan_tiles((1024, 2048), 1000.0, margin=56, max_bytes=1000 * 830_000)
    assert plan_summary((1024, 2048), plan) == {"tile": (1024, 768), "tiles": 3,
                                                "computed": 1.125}


def test_plan_counts_the_output_and_the_allocator():
    from mehs.ssr.tiling import plan_summary

    shape, bpp = (1024, 2048), 1000.0
    # fits whole: the stitched output is not needed
    assert plan_tiles(shape, bpp, margin=8, max_bytes=bpp * 2**21, out_bytes=1e9).tile is None
    base = plan_summary(shape, plan_tiles(shape, bpp, margin=8, max_bytes=bpp * 600_000))
    less = plan_summary(shape, plan_tiles(shape, bpp, margin=8, max_bytes=bpp * 600_000,
                                          out_bytes=bpp * 300_000))
    doubled = plan_summary(shape, plan_tiles(shape, bpp, margin=8, max_bytes=bpp * 600_000,
                                             overhead=lambda n: 2.0))
    for s in (less, doubled):
        assert s["tile"][0] * s["tile"][1] <= 300_000 < base["tile"][0] * base["tile"][1]


def test_default_budget_is_the_cap_less_what_the_process_holds(monkeypatch):
    from mehs.ssr import tiling

    monkeypatch.setattr(tiling, "_rss", lambda: 500_000_000)
    monkeypatch.setattr(tiling, "available_memory", lambda: 8_000_000_000)
    assert tiling.default_budget(2_000_000_000) == 1_500_000_000
    assert tiling.default_budget() == tiling.DEFAULT_MAX_RSS - 500_000_000
    monkeypatch.setattr(tiling, "available_memory", lambda: 1_000_000_000)
    assert tiling.default_budget(2_000_000_000) == 500_000_000      # half the available
    monkeypatch.setattr(tiling, "available_memory", lambda: 8_000_000_000)
    monkeypatch.setattr(tiling, "_rss", lambda: 2_500_000_000)      # already over the cap
    assert tiling.default_budget(2_000_000_000) == tiling.MIN_BUDGET


def test_network_call_budget_leaves_room_for_the_output(monkeypatch):
    from mehs.ssr import tiling

    monkeypatch.setattr(tiling, "_rss", lambda: 0)
    monkeypatch.setattr(tiling, "available_memory", lambda: 1 << 40)
    monkeypatch.delenv("MEHS_TILE_MEMORY", raising=False)
    probes = {"bytes_per_pixel": lambda: {"bytes_per_pixel": 100.0, "fixed_bytes": 0.0,
                                          "out_bytes_per_pixel": 16.0},
              "margin": lambda: 8, "align": lambda: 8}
    fn = lambda x: np.repeat(x[:, :, :1] * 2, 4, axis=2)                # noqa: E731
    rgb = _rgb(400, 600)
    model = SimpleNamespace(tiling={"max_rss": 10_000_000})             # whole: 24 MB
    out = tiling.tiled_network_call(model, fn, rgb, probes)
    np.testing.assert_allclose(out, fn(rgb), rtol=1e-6)
    last = model._tiling_last
    th, tw = last["summary"]["tile"]
    assert last["budget"] == 10_000_000 and last["out_bytes"] == 400 * 600 * 16
    assert 100 * th * tw <= 10_000_000 - 400 * 600 * 16 < 100 * 400 * 600
    # MEHS_TILE_MEMORY is the tile's own budget: no room is kept for the output
    monkeypatch.setenv("MEHS_TILE_MEMORY", str(10_000_000 / 2**20))
    model = SimpleNamespace(tiling="auto", _tiling_probe={})
    tiling.tiled_network_call(model, fn, rgb, probes)
    th2, tw2 = model._tiling_last["summary"]["tile"]
    assert model._tiling_last["out_bytes"] == 0 and th2 * tw2 > th * tw


def test_blend_keeps_band_major_tiles_band_major():
    # torch hands back (h, w, B) views of (B, h, w) buffers: the stitched image is laid
    # out the same way (as whole-image inference returns it), with the same values
    rgb = _rgb(97, 131)

    def fn(x):
        y = np.stack([x[:, :, 0] * np.float32(k + 1) for k in range(5)])    # (B, h, w)
        return y.transpose(1, 2, 0)

    plan = TilingPlan(48, 4, 8, 8, tile_w=64)
    out = predict_tiled(fn, rgb, plan)
    assert out.shape == (97, 131, 5) and out.transpose(2, 0, 1).flags.c_contiguous
    np.testing.assert_allclose(out, fn(rgb), rtol=1e-6)
    out = predict_tiled(lambda x: np.ascontiguousarray(fn(x)), rgb, plan)
    assert out.flags.c_contiguous
    np.testing.assert_allclose(out, fn(rgb), rtol=1e-6)


def test_memory_probe_of_chunked_branches_does_not_depend_on_probe_size():
    # the basis branches work in chunks of 32 k pixels: probes below that size
    # measured the branch's growth up to the chunk as memory per pixel (1.37 kB/px
    # for small hdrssr, 0.90 for a large image). The probe's chunks are small, so any
    # two probe sizes give the large-image slope, and the branches' own setting is back
    from mehs.ssr.net.basis import _BasisBranch
    from mehs.ssr.net.zoo import build_network

    torch.manual_seed(0)
    net = build_network(arch="hdrssr", preset="tiny").eval()
    net.hat_branch.chunk_pixels = 5000               # an instance's own setting survives
    small = torch_memory_probe(net, sizes=(96, 128))
    large = torch_memory_probe(net, sizes=(192, 256))
    assert small["bytes_per_pixel"] == pytest.approx(large["bytes_per_pixel"], rel=0.03)
    assert net.hat_branch.chunk_pixels == 5000
    assert "chunk_pixels" not in vars(net.sigmoid_branch)
    assert net.sigmoid_branch.chunk_pixels == _BasisBranch.chunk_pixels
    # and the line covers a run with the branches' own chunks above the probes
    from mehs.ssr.tiling_probes import _peak_tensor_bytes

    peak, _ = _peak_tensor_bytes(net, 320)
    assert peak <= large["fixed_bytes"] + large["bytes_per_pixel"] * 320 ** 2


def test_tiles_run_on_the_reused_heap_planned_for_its_memory(monkeypatch):
    """A network whose probe models glibc's heap gets tiles on the reused heap, sized with
    :func:`heap_reuse_overhead`; one without that model keeps the default allocator."""
    from mehs.ssr import allocator, tiling

    if not allocator.heap_reuse_available():
        pytest.skip("not glibc")
    monkeypatch.setattr(tiling, "_rss", lambda: 0)
    monkeypatch.setattr(tiling, "available_memory", lambda: 1 << 40)
    monkeypatch.delenv("MEHS_TILE_MEMORY", raising=False)
    acted = []
    real = allocator.reused_heap

    def spy(enable=True):
        acted.append(enable)
        return real(enable)

    monkeypatch.setattr(tiling, "reused_heap", spy)
    fn = lambda x: np.repeat(x[:, :, :1] * 2, 4, axis=2)                # noqa: E731
    rgb = _rgb(400, 600)
    for kind in ("heap", None):
        probes = {"bytes_per_pixel": lambda: {"bytes_per_pixel": 100.0, "fixed_bytes": 1e5,
                                              "out_bytes_per_pixel": 16.0, "allocator": kind},
                  "margin": lambda: 8, "align": lambda: 8}
        model = SimpleNamespace(tiling={"max_rss": 20_000_000})
        np.testing.assert_allclose(tiling.tiled_network_call(model, fn, rgb, probes), fn(rgb),
                                   rtol=1e-6)
        last = model._tiling_last
        th, tw = last["summary"]["tile"]
        model_of = (allocator.heap_reuse_overhead if kind == "heap"
                    else lambda n: 1.0)
        assert last["heap_reuse"] is (kind == "heap")
        assert (1e5 + 100 * th * tw) * model_of(th * tw) + last["out_bytes"] <= last["budget"]
    assert acted == [True, False]


def test_reused_heap_serves_arrays_from_the_heap_and_settles_after():
    """Inside :func:`reused_heap` a 20 MB array comes from glibc's heap (``arena``), not a
    mapping of its own; after it the thresholds sit where glibc's dynamic ones settle
    (a 20 MB array from the heap, a 40 MB one mapped) and the free heap is returned."""
    import subprocess
    import sys

    code = MALLINFO2 + (
        "import numpy as np\n"
        "from mehs.ssr.allocator import reused_heap\n"
        "with reused_heap() as on:\n"
        "    a = np.ones(75_000_000, np.uint8)\n"
        "    m = libc.mallinfo2()\n"
        "    print('IN', on, m.arena >= 75_000_000, m.hblkhd < 75_000_000)\n"
        "    del a\n"
        "m = libc.mallinfo2()\n"
        "print('TRIMMED', m.arena < 20_000_000)\n"
        "b = np.ones(20_000_000, np.uint8); c = np.ones(40_000_000, np.uint8)\n"
        "m = libc.mallinfo2()\n"
        "print('AFTER', m.arena >= 20_000_000, 40_000_000 <= m.hblkhd < 60_000_000)\n")
    if not has_mallinfo2():
        pytest.skip("not glibc ≥ 2.33")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    assert "IN True True True" in r.stdout
    assert "TRIMMED True" in r.stdout
    assert "AFTER True True" in r.stdout, r.stdout
