"""Tiles that equal the whole image for MST++'s spectral-wise attention, and for networks
that pad to their pooling grid inside (issue 16: output equal to whole-image inference to
1e-5 away from the borders)."""

import warnings
from types import SimpleNamespace

import numpy as np
import pytest
from _checks import contrast_rgb

torch = pytest.importorskip("torch")
torch.set_num_threads(1)

from mehs.ssr.net import ChannelAttention, build_network  # noqa: E402
from mehs.ssr.net.mstpp2022 import SpectralMSA  # noqa: E402
from mehs.ssr.tiling_probes import GLOBAL_MARGIN, torch_align, torch_receptive_radius  # noqa: E402
from mehs.ssr.tiling import TilingPlan, tile_starts  # noqa: E402
from mehs.ssr.tiling_torch import tiled_torch_call  # noqa: E402


def _run(net, rgb, **tiling):
    model = SimpleNamespace(network=net, device="cpu", name="net", tiling=tiling or "off")
    return tiled_torch_call(model, rgb), model


def _sharp_mst(seed=0, num_blocks=(1, 1, 1)):
    """MST++ with two U-Net levels, its attention made strongly image-dependent, as
    training makes it: at initialisation (σ = 1, projection weights of std 0.02) the
    attention hardly reaches the output, and a tile's own similarity would pass any test."""
    torch.manual_seed(seed)
    net = build_network(arch="mstpp", preset="tiny", levels=2, num_blocks=num_blocks).eval()
    with torch.no_grad():
        for m in net.modules():
            if isinstance(m, SpectralMSA):
                m.rescale.fill_(8.0)
                m.proj.weight.mul_(20.0)
    return net


def test_the_field_probe_sees_mst_as_local_once_its_similarity_is_detached():
    # the channel similarity sums over every pixel: before, the probe's gradient filled
    # every probe up to 512 px and MST++ counted as a global operation (each tile its own
    # attention); the local part is the convolutions' field
    net = _sharp_mst()
    margin = torch_receptive_radius(net, align=torch_align(net))
    assert 0 < margin < GLOBAL_MARGIN
    assert margin % torch_align(net) == 0


@pytest.mark.parametrize("shape,budget", [((64, 400), 64 * 208),       # strips
                                          ((161, 203), 120 * 136)])     # a grid, odd sizes
def test_mst_tiles_with_the_image_similarity_equal_the_whole_image(shape, budget):
    net = _sharp_mst()
    margin = torch_receptive_radius(net, align=8)
    rgb = contrast_rgb(*shape)
    whole, _ = _run(net, rgb)
    opts = dict(bytes_per_pixel=1.0, max_bytes=budget, blend=16, margin=margin, align=8)
    per_tile, m1 = _run(net, rgb, statistics="tile", **opts)
    with warnings.catch_warnings():
        warnings.simplefilter("error", RuntimeWarning)        # the statistics settle
        image, m2 = _run(net, rgb, **opts)                     # the default: "auto"
    assert m2._tiling_last["summary"]["tiles"] >= 3
    th, tw = m2._tiling_last["summary"]["tile"]
    overlap = TilingPlan(th, margin, 16, 8, tw).overlap
    rows, cols = (len(tile_starts(n, t, overlap, 8)) for n, t in zip(shape, (th, tw)))
    if shape == (64, 400):
        assert rows == 1 and cols >= 3                                      # strips
    else:
        assert rows >= 3 and cols >= 3      # a 2-D grid with a tile inside on every side
    assert m2._tiling_last["statistics"] == "image" and m1._tiling_last["statistics"] == "tile"
    scale = np.abs(whole).max()
    assert np.abs(per_tile - whole).max() > 1e-3 * scale       # what the image's are for
    np.testing.assert_allclose(image, whole, rtol=0, atol=1e-5 * scale)
    # "image" (strict) no longer refuses MST++
    strict, _ = _run(net, rgb, statistics="image", **opts)
    np.testing.assert_allclose(strict, whole, rtol=0, atol=1e-5 * scale)


@pytest.mark.parametrize("chunk", [1 << 16, 7])
def test_spectral_attention_outside_tiles_is_unchanged(chunk, monkeypatch):
    # the attention's own path (no tiling context) and its image-statistics path agree,
    # its sums taken in one piece or in chunks of a row
    from mehs.ssr.net import mstpp2022
    from mehs.ssr.net.pooling import ImageMeans

    monkeypatch.setattr(mstpp2022, "SIMILARITY_CHUNK", chunk)

    torch.manual_seed(1)
    msa = SpectralMSA(62, 31, 2).eval()
    with torch.no_grad():
        msa.to_q.weight.mul_(10.0)
        msa.to_k.weight.mul_(10.0)
    x = torch.randn(1, 12, 20, 62)
    with torch.no_grad():
        own = msa(x)
        means = ImageMeans()
        with means.active():
            means.enter((0, 12), (0, 20), (0, 12), (0, 20), True, True)
            first = msa(x)                       # the first run: its own similarity
            means.finish()
            means.enter((0, 12), (0, 20), (0, 12), (0, 20), True, True)
            second = msa(x)                      # the image's, assembled from one tile
            assert means.finish() < 1e-6
    torch.testing.assert_close(first, own, rtol=0, atol=0)
    torch.testing.assert_close(second, own, rtol=1e-5, atol=1e-5)


def _deep_attention_net(seed=0, down_layers=(1, 1, 1, 1), **params):
    """The paper's network, four poolings deep (grid 16, as the full preset's 32), channel
    attention at every level and made image-dependent; it pads to its grid inside."""
    torch.manual_seed(seed)
    net = build_network(arch="hdrssr", preset="tiny", down_layers=down_layers,
                        **params).eval()
    with torch.no_grad():
        for m in net.modules():
            if isinstance(m, ChannelAttention):
                m.squeeze.weight.mul_(20.0)
                m.excite.weight.mul_(20.0)
    return net


@pytest.mark.parametrize("width", [300, 357])
def test_last_tiles_off_the_grid_of_a_network_that_pads_inside(width):
    # an image whose width is no multiple of the grid: the last tile's pooled maps cover
    # it padded by the network itself. Before, their cells were sized ceil(n / m): a
    # 108-pixel tile's 16-cell map read as 7-pixel cells, and image-wide means were
    # refused (the paper's full-size network on any image not a multiple of 32 wide)
    net = _deep_attention_net()
    align = torch_align(net)
    assert align == 16
    margin = torch_receptive_radius(net, align=align)
    rgb = contrast_rgb(48, width, seed=5)
    whole, _ = _run(net, rgb)
    image, m = _run(net, rgb, bytes_per_pixel=1.0, max_bytes=48 * (2 * margin + 16 + 64 + 8),
                    blend=16, statistics="image", margin=margin)
    plan = m._tiling_last["plan"]
    assert m._tiling_last["summary"]["tiles"] >= 2 and width % align != 0
    assert plan.width % align == 0
    np.testing.assert_allclose(image, whole, rtol=0, atol=1e-5 * np.abs(whole).max())


def test_onnx_last_tile_off_the_grid_of_a_network_that_pads_inside(tmp_path):
    # the same for an exported graph (grid 32, as the full-size paper network's): the
    # graph sized the last tile's cells ceil(tile / map) in the graph itself, and a
    # 357-pixel-wide image was refused; the cells learnt from the first tile are fed in
    pytest.importorskip("onnxruntime")
    pytest.importorskip("onnx")
    from mehs.ssr.models import load_model
    from mehs.ssr.net.export import TorchSSRModel, export_onnx

    net = _deep_attention_net(seed=4, down_layers=(1, 1, 1, 1, 1), mode="e2e")
    assert torch_align(net) == 32
    margin = torch_receptive_radius(net, align=32)
    model = load_model(str(export_onnx(TorchSSRModel(net), tmp_path / "deep.onnx")))
    rgb = contrast_rgb(48, 357, seed=5)
    model.tiling = "off"
    whole = model(rgb)
    model.tiling = dict(bytes_per_pixel=1.0, max_bytes=48 * 352, blend=16, margin=margin,
                        align=32, statistics="image")
    tiled = model(rgb)
    assert model._tiling_last["summary"]["tiles"] >= 2
    assert model._tiling_last["statistics"] == "image"
    np.testing.assert_allclose(tiled, whole, rtol=0, atol=1e-5 * np.abs(whole).max())


def test_a_real_64_pixel_field_is_not_taken_for_a_global_operation():
    # MST++ with a 3-block bottleneck has a 64-pixel field on the 8-grid, the margin that
    # used to mark "global": each tile then got its own similarity (2e-3 off), silently
    net = _sharp_mst(num_blocks=(1, 1, 3))
    margin = torch_receptive_radius(net, align=8)
    assert margin == 64 != GLOBAL_MARGIN
    rgb = contrast_rgb(24, 400, seed=2)
    whole, _ = _run(net, rgb)
    model = SimpleNamespace(network=net, device="cpu", name="mst",
                            tiling=dict(bytes_per_pixel=1.0, max_bytes=24 * 232, blend=16),
                            _tiling_probe={"margin": margin, "align": 8})
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        tiled = tiled_torch_call(model, rgb)
    assert model._tiling_last["statistics"] == "image"
    assert model._tiling_last["summary"]["tiles"] >= 2
    np.testing.assert_allclose(tiled, whole, rtol=0, atol=1e-5 * np.abs(whole).max())


def test_mst_declares_its_pooling_grid():
    # four levels pad to 16 inside: tiles on an 8-grid started off the network's grid
    net = build_network(arch="mstpp", preset="tiny", levels=4, num_blocks=(1, 1, 1, 1, 1))
    assert torch_align(net) == 16 == net.multiple


@pytest.mark.parametrize("dtype", [torch.float16, torch.bfloat16])
def test_half_float_attention_statistics_do_not_overflow(dtype):
    # the Gram matrix of a half-float tile was summed in half floats: inf, then NaN output
    # and a run that counted as settled
    from mehs.ssr.net.pooling import ImageMeans

    torch.manual_seed(1)
    msa = SpectralMSA(62, 31, 2).eval()
    with torch.no_grad():
        msa.to_q.weight.mul_(10.0)
        msa.to_k.weight.mul_(10.0)
    msa = msa.to(dtype)
    x = torch.randn(1, 64, 80, 62).to(dtype)
    with torch.no_grad():
        own = msa(x).float()
        means = ImageMeans()
        with means.active():
            for _ in range(2):
                means.enter((0, 64), (0, 80), (0, 64), (0, 80), True, True)
                second = msa(x).float()
                change = means.finish()
    assert torch.isfinite(second).all() and change < 1e-2
    tol = 2e-3 if dtype is torch.float16 else 2e-2
    assert float((second - own).abs().max() / own.abs().max()) < tol
