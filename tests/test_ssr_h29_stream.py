"""HSCNN-D inference streamed down the rows (issue 16): every feature row computed once,
a window of rows alive, the plain graph's numbers; its memory, growing with the width
only, measured by the memory probe and planned by the tiling."""

import numpy as np
import pytest
from _checks import peak_live_bytes

torch = pytest.importorskip("torch")
torch.set_num_threads(1)

from torch import nn  # noqa: E402

from mehs.ssr.net import build_network  # noqa: E402
from mehs.ssr.net import hscnnd_stream  # noqa: E402
from mehs.ssr.net.hscnnd2018 import HSCNND2018  # noqa: E402


def _net(preset="tiny", seed=0, **params):
    torch.manual_seed(seed)
    return build_network(arch="hscnnd", preset=preset, **params).eval()


def _plain(net, x):
    # the training graph: dense features concatenated after every block
    return net(x.clone().requires_grad_()).detach()


def _close(got, want):
    torch.testing.assert_close(got, want, rtol=1e-5, atol=1e-5 * float(want.abs().max()))


@pytest.mark.parametrize("preset", ["tiny", "small"])
@pytest.mark.parametrize("h", [1, 2, 7, 34, 35, 36, 64, 97])
def test_streamed_inference_gives_the_plain_graphs_numbers(preset, h):
    # heights below, at and past the window, and several steps (tiny: 32-row steps,
    # 35-row window; small: 39), two images of the batch
    net = _net(preset)
    x = torch.rand(2, 3, h, 11) * 5
    with torch.no_grad():
        got = net(x)
    _close(got, _plain(net, x))


def test_wider_blocks_and_a_float64_network():
    # steps of n + 2 rows where that passes 32 (40 blocks); float64 kept to its precision
    net = _net("tiny", n_blocks=40).double()
    assert hscnnd_stream.step_rows(net) == 42
    x = torch.rand(1, 3, 130, 6, dtype=torch.float64) * 5
    with torch.no_grad():
        got = net(x)
    want = _plain(net, x)
    assert got.dtype == torch.float64
    torch.testing.assert_close(got, want, rtol=1e-12, atol=1e-12)


def test_every_feature_row_is_computed_once(monkeypatch):
    # a wavefront, not tiles: each block's new channels are made for each image row
    # exactly once however many steps there are
    net = _net("small")
    made = []
    real = hscnnd_stream._block

    def counting(block, buf, c, a, b, base, h):
        made.append((c, a, b))
        return real(block, buf, c, a, b, base, h)

    monkeypatch.setattr(hscnnd_stream, "_block", counting)
    h = 150
    with torch.no_grad():
        net(torch.rand(1, 3, h, 9))
    for c in {c for c, _, _ in made}:
        spans = sorted((a, b) for cc, a, b in made if cc == c)
        rows = [r for a, b in spans for r in range(a, b)]
        assert rows == list(range(h)), c


def test_the_window_not_the_image_sets_the_memory():
    # the dense features of a 4× taller image cost 4× the bytes; streamed, only its input
    # and output grow (3 + 3 + 31 channels of float32 per pixel: 148 B)
    net = _net("small")
    x1, x2 = torch.rand(1, 3, 100, 40), torch.rand(1, 3, 400, 40)
    with torch.no_grad():
        p1 = peak_live_bytes(lambda: net(x1))
        p2 = peak_live_bytes(lambda: net(x2))
    features = (net.c0 + len(net.blocks) * net.fuse) * 4
    assert p2 - p1 <= 160 * (400 - 100) * 40
    assert p1 < features * 100 * 40                  # less than the dense features


def test_a_changed_network_runs_its_parts():
    # a subclass, a hook or a block put in its place is run by its modules (its forward,
    # its hooks), not by the streaming's direct calls
    x = torch.rand(1, 3, 70, 9) * 5

    class Mine(HSCNND2018):
        pass

    net = _net("tiny")
    sub = _net("tiny")
    sub.__class__ = Mine
    calls = []
    hooked = _net("tiny")
    hooked.blocks[1].fusion.register_forward_hook(lambda m, i, o: calls.append(o.shape))
    replaced = _net("tiny")
    replaced.blocks[0] = nn.Sequential(replaced.blocks[0])
    for n in (sub, hooked, replaced):
        assert not hscnnd_stream.streamable(n)
        with torch.no_grad():
            got = n(x)
        _close(got, _plain(n, x))
    assert calls
    with torch.no_grad():
        _close(net(x), sub(x))


def test_gradients_take_the_plain_graph():
    net = _net("tiny")
    x = torch.rand(1, 3, 80, 8, requires_grad=True)
    net(x).sum().backward()
    assert x.grad is not None and float(x.grad.abs().sum()) > 0


def test_chunk_pixels_zero_keeps_the_dense_features():
    net = _net("tiny")
    net.chunk_pixels = 0
    assert net.stream_window_rows(64) == 0
    x = torch.rand(1, 3, 80, 8)
    with torch.no_grad():
        _close(net(x), _plain(net, x))


def _counted_model(model, h, w):
    return (model["fixed_bytes"] + model["bytes_per_pixel"] * h * w
            + model.get("bytes_per_column", 0.0) * w)


@pytest.mark.parametrize("preset", ["tiny", "small"])
def test_the_memory_probe_measures_the_window_per_column(preset):
    # square probes took the window for memory per pixel: a line through 96² and 128²
    # put HSCNN-D full at 2.6 GB for 2048×1024, whose streamed inference holds 0.97 GB
    from mehs.ssr.tiling_probes import torch_memory_probe

    net = _net(preset)
    model = torch_memory_probe(net)
    assert model["bytes_per_column"] > 0
    for h, w in ((300, 50), (60, 400), (500, 120), (20, 300), (1, 64)):
        with torch.no_grad():
            counted = peak_live_bytes(lambda: net(torch.rand(1, 3, h, w)))
        predicted = _counted_model(model, h, w)
        assert counted <= 1.02 * predicted, (h, w)
        if h >= 300:                                # (a short image holds less window)
            assert predicted <= 1.25 * counted, (h, w)


def test_the_library_runs_a_tall_image_whole_within_the_budget(tmp_path, monkeypatch):
    # the budget holds the window (per column) and the image's in- and output, not the
    # dense features: untiled; a budget under the streamed call's tiles
    from mehs.ssr.net.export import TorchSSRModel

    monkeypatch.setenv("MEHS_CACHE_DIR", str(tmp_path))
    net = _net("small")
    model = TorchSSRModel(net)
    rgb = (torch.rand(960, 64, 3) * 4).numpy()
    model.tiling = "off"
    whole = model.standard_spectrum(rgb)
    features = (net.c0 + len(net.blocks) * net.fuse) * 4 * 960 * 64
    model.tiling = {"max_bytes": int(features * 0.7)}
    got = model.standard_spectrum(rgb)
    assert model._tiling_last["plan"] is None
    np.testing.assert_array_equal(got, whole)
    from mehs.ssr.allocator import allocator_overhead

    m = model._tiling_probe
    need = (m["fixed_bytes"] + m["bytes_per_pixel"] * 960 * 64
            + m["bytes_per_column"] * 64) * allocator_overhead(960 * 64)
    model.tiling = {"max_bytes": int(need * 0.6)}
    tiled = model.standard_spectrum(rgb)
    assert model._tiling_last["summary"]["tiles"] > 1
    np.testing.assert_allclose(tiled, whole, rtol=0, atol=1e-5 * np.abs(whole).max())


def test_a_hooked_network_gets_its_own_memory_model(tmp_path, monkeypatch):
    # a hook turns streaming off (the dense features, many times the window): the plain
    # network's cached memory model planned a hooked one to run whole, 2.4x over budget
    from mehs.ssr.net.export import TorchSSRModel

    monkeypatch.setenv("MEHS_CACHE_DIR", str(tmp_path))
    rgb = (torch.rand(600, 40, 3) * 4).numpy()
    plain = TorchSSRModel(_net("small"))
    plain.tiling = {"max_bytes": 10**12}
    plain.standard_spectrum(rgb)
    hooked_net = _net("small")
    hooked_net.blocks[0].register_forward_hook(lambda m, i, o: None)
    hooked = TorchSSRModel(hooked_net)
    hooked.tiling = {"max_bytes": 10**12}
    hooked.standard_spectrum(rgb)
    per_pixel = hooked._tiling_probe["bytes_per_pixel"]
    assert per_pixel > 4 * plain._tiling_probe["bytes_per_pixel"]
    # the same model object, hooked after its first call, is probed again
    handle = plain.network.blocks[1].register_forward_hook(lambda m, i, o: None)
    plain.standard_spectrum(rgb)
    assert plain._tiling_probe["bytes_per_pixel"] == per_pixel
    handle.remove()
    plain.standard_spectrum(rgb)
    assert plain._tiling_probe["bytes_per_pixel"] < per_pixel / 4


def test_a_grouped_convolution_in_a_block_is_run_by_its_module():
    net = _net("tiny")
    b = net.blocks[1]
    b.up1 = nn.Conv2d(b.up1.in_channels, b.up1.out_channels, 3, padding=1, groups=2,
                      bias=False)
    assert not hscnnd_stream.streamable(net)
    x = torch.rand(1, 3, 40, 9)
    with torch.no_grad():
        _close(net(x), _plain(net, x))


def test_the_column_term_can_be_given_as_a_tiling_option():
    from mehs.ssr.net.export import TorchSSRModel

    model = TorchSSRModel(_net("tiny"))
    rgb = (torch.rand(300, 200, 3) * 4).numpy()
    model.tiling = {"bytes_per_pixel": 200.0, "column_bytes": 20000.0,
                    "max_bytes": 200 * 300 * 200, "statistics": "tile"}
    model.standard_spectrum(rgb)
    assert model._tiling_last["summary"]["tiles"] > 1


def test_export_with_a_dynamic_height_takes_the_plain_graph():
    # torch.export under no_grad traced the streaming's row loop for one height
    from torch.export import Dim, export

    net = _net("tiny")
    with torch.no_grad():
        ep = export(net, (torch.rand(1, 3, 80, 16),),
                    dynamic_shapes=({2: Dim("h", min=2, max=4096),
                                     3: Dim("w", min=2, max=4096)},))
    x = torch.rand(1, 3, 123, 20)
    _close(ep.module()(x), _plain(net, x))


def test_a_model_under_autocast_or_hooked_later_is_probed_again(tmp_path, monkeypatch):
    # the streamed memory model kept by a model object planned its autocast call (the
    # plain dense graph) to run whole 1.6x over budget; a hook added later kept the
    # margin measured without it
    from mehs.ssr import tiling_torch
    from mehs.ssr.net.export import TorchSSRModel

    monkeypatch.setenv("MEHS_CACHE_DIR", str(tmp_path))
    model = TorchSSRModel(_net("small"))
    rgb = (torch.rand(600, 40, 3) * 4).numpy()
    model.tiling = {"max_bytes": 10**12}
    model.standard_spectrum(rgb)
    streamed = model._tiling_probe["bytes_per_pixel"]
    with torch.autocast("cpu", dtype=torch.bfloat16):
        model.standard_spectrum(rgb)
    assert model._tiling_probe["bytes_per_pixel"] > 4 * streamed
    margins = []
    real = tiling_torch.torch_receptive_radius
    monkeypatch.setattr(tiling_torch, "torch_receptive_radius",
                        lambda *a, **k: margins.append(1) or real(*a, **k))
    model.tiling = {"bytes_per_pixel": 400.0, "max_bytes": 400 * 160 * 40}
    model.standard_spectrum(rgb)
    assert len(margins) == 1 and model._tiling_last["summary"]["tiles"] > 1
    model.standard_spectrum(rgb)
    assert len(margins) == 1                       # kept while nothing changed
    model.network.blocks[0].register_forward_hook(lambda m, i, o: None)
    model.standard_spectrum(rgb)
    assert len(margins) == 2
