"""Lean inference, session 27 (issue 16): transposed convolutions in row strips."""

import itertools
import warnings

import numpy as np

import pytest

torch = pytest.importorskip("torch")
torch.set_num_threads(1)

from torch import nn  # noqa: E402

from mehs.ssr.net import build_network  # noqa: E402
from mehs.ssr.net.strips import conv_transpose_into  # noqa: E402


CONFIGS = [(k, s, p, d, op) for k, s, p, d, op in itertools.product(
    (1, 2, 3, 4), (1, 2, 3), (0, 1, 2), (1, 2), (0, 1, 2)) if op < max(s, d) and p <= d * (k - 1)]


@pytest.mark.parametrize("k,s,p,d,op", CONFIGS)
def test_strips_of_a_transposed_convolution_are_the_whole_call(k, s, p, d, op):
    # every strip's output rows, with bias-only rows no input reaches (p large, k small)
    torch.manual_seed(k * 100 + s * 10 + p)
    for bias in (True, False):
        up = nn.ConvTranspose2d(3, 4, k, stride=s, padding=p, output_padding=op, dilation=d,
                                bias=bias)
        x = torch.randn(2, 3, 6, 5)
        with torch.no_grad():
            want = up(x)
            for pixels in (1, 2 * want.shape[3], 5 * want.shape[3]):
                got = torch.full_like(want, float("nan"))
                conv_transpose_into(up, x, got, pixels)
                torch.testing.assert_close(got, want, rtol=1e-5, atol=1e-6)


def test_a_module_with_a_hook_or_a_wrong_destination_runs_whole():
    up = nn.ConvTranspose2d(3, 4, 3, stride=2, padding=1, output_padding=1)
    x = torch.randn(1, 3, 6, 5)
    seen = []
    up.register_forward_hook(lambda m, i, o: seen.append(o.shape))
    with torch.no_grad():
        dst = torch.empty(1, 4, 12, 10)
        conv_transpose_into(up, x, dst, 10)
        assert seen == [torch.Size([1, 4, 12, 10])]
        with pytest.raises(RuntimeError):
            conv_transpose_into(up, x, torch.empty(1, 4, 11, 10), 10)


def _largest_transposed_output(net, x):
    from torch.utils._python_dispatch import TorchDispatchMode

    class Watch(TorchDispatchMode):
        largest = 0

        def __torch_dispatch__(self, func, types, args=(), kwargs=None):
            out = func(*args, **(kwargs or {}))
            if func is torch.ops.aten.convolution.default and args[6]:     # transposed
                Watch.largest = max(Watch.largest, out.shape[-2] * out.shape[-1])
            return out

    with torch.no_grad(), Watch():
        net(x)
    return Watch.largest


@pytest.mark.parametrize("arch", ["hdrssr", "galliani"])
def test_fc_densenet_upsamples_in_strips(arch):
    # CPU transposed convolutions gather through a C_out·k² column buffer per input
    # pixel: FC-DenseNet56's last one held 0.9 GB at 2048×1024, its inference's peak
    torch.manual_seed(0)
    net = build_network(arch=arch, preset="tiny").eval()
    net.features.chunk_pixels = 64 * 8
    x = torch.rand(1, 3, 64, 64)
    # (a strip computes the rows its input rows reach: a few more than it keeps)
    assert 0 < _largest_transposed_output(net, x) <= 2 * 64 * 8
    with torch.no_grad():
        lean = net(x)
    plain = net(x.clone().requires_grad_()).detach()
    torch.testing.assert_close(lean, plain, rtol=1e-6, atol=1e-6 * float(plain.abs().max()))


def _chunked(net, pixels):
    for m in net.modules():
        if isinstance(getattr(m, "chunk_pixels", None), int):
            m.chunk_pixels = pixels


def _lean_and_plain(net, x):
    with torch.no_grad():
        lean = net(x)
    plain = net(x.clone().requires_grad_()).detach()
    return lean, plain


@pytest.mark.parametrize("preset,n,shape,rows", [("tiny", 1, (45, 37), 3), ("full", 1, (40, 64), 3),
                                                 ("small", 2, (33, 24), 3), ("tiny", 1, (16, 8), 0)])
def test_mstpp_strips_give_the_plain_graphs_numbers(preset, n, shape, rows):
    # strips of a few rows: every attention block's positional term and every
    # feed-forward block's depth-wise convolution reads context rows across strips
    from mehs.ssr.net.mstpp2022 import MSAB

    torch.manual_seed(5)
    net = build_network(arch="mstpp", preset=preset).eval()
    with torch.no_grad():                      # attention that mixes channels unevenly
        for m in net.modules():
            if hasattr(m, "rescale"):
                m.rescale.fill_(4.0)
    x = torch.rand(n, 3, *shape) * 10
    # (rows=0: one row per strip, fewer than the context rows the strips overwrite later)
    _chunked(net, rows * shape[1] or 1)
    blocks = [m for m in net.modules() if type(m) is MSAB]
    with torch.no_grad():
        assert blocks and all(b._strippable() for b in blocks)
    lean, plain = _lean_and_plain(net, x)
    torch.testing.assert_close(lean, plain, rtol=1e-5, atol=1e-5 * float(plain.abs().max()))


CONV_CONFIGS = [(k, s, p, d) for k, s, p, d in itertools.product((1, 2, 3, 4), (1, 2, 3), (0, 1, 2, 4), (1, 2))]


@pytest.mark.parametrize("k,s,p,d", CONV_CONFIGS)
def test_strips_of_a_convolution_are_the_whole_call(k, s, p, d):
    from mehs.ssr.net.strips import conv2d_into

    torch.manual_seed(k + 7 * s + 31 * p)
    conv = nn.Conv2d(3, 4, k, stride=s, padding=p, dilation=d)
    x = torch.randn(2, 3, 9, 6)
    with torch.no_grad():
        try:
            want = conv(x)
        except RuntimeError:                   # a kernel wider than the padded image
            return
        extra = torch.randn_like(want)
        for pixels in (1, 2 * want.shape[3], 5 * want.shape[3]):
            got = conv2d_into(conv, x, chunk_pixels=pixels)
            torch.testing.assert_close(got, want, rtol=1e-5, atol=1e-6)
            out = torch.full_like(want, float("nan"))
            conv2d_into(conv, x, out, add=extra, chunk_pixels=pixels)
            torch.testing.assert_close(out, want + extra, rtol=1e-5, atol=1e-6)


def test_a_same_padded_or_hooked_convolution_runs_whole():
    from mehs.ssr.net.strips import conv2d_into

    x = torch.randn(1, 3, 9, 6)
    with torch.no_grad():
        for conv in (nn.Conv2d(3, 4, 3, padding="same"), nn.Conv2d(3, 4, 3, padding=1,
                                                                   padding_mode="reflect")):
            torch.testing.assert_close(conv2d_into(conv, x, chunk_pixels=6), conv(x))


@pytest.mark.parametrize("arch,preset", [("hscnnd", "tiny"), ("hscnnd", "small"),
                                         ("galliani", "tiny")])
@pytest.mark.parametrize("rows", [1, 4])
def test_hscnnd_and_galliani_strips_give_the_plain_graphs_numbers(arch, preset, rows):
    # HSCNN-D's blocks (two 3×3 convolutions of the compressed map) and output
    # convolution, Galliani's 1×1 head, in strips of one and of four rows
    torch.manual_seed(6)
    net = build_network(arch=arch, preset=preset).eval()
    x = torch.rand(2, 3, 23, 17) * 5
    _chunked(net, rows * 17 * 2)
    lean, plain = _lean_and_plain(net, x)
    torch.testing.assert_close(lean, plain, rtol=1e-5, atol=1e-5 * float(plain.abs().max()))


def test_hscnnd_blocks_run_in_strips(monkeypatch):
    # a whole-map block held its compression's reordered copy of up to 1056 channels
    from mehs.ssr.net.hscnnd2018 import DenseFusionBlock

    from mehs.ssr.net.hscnnd2018 import HSCNND2018

    class Own(HSCNND2018):
        """(a subclass keeps the dense features: plain ones are streamed, session 29)"""

    torch.manual_seed(0)
    net = build_network(arch="hscnnd", preset="tiny").eval()
    net.__class__ = Own
    # (strips hold chunk_pixels · 128 / channels pixels: at least 32 channels here, so
    # at most 4 rows of 32)
    net.chunk_pixels = 32
    rows = []
    plain_forward = DenseFusionBlock.forward

    def counting(self, x):
        rows.append(x.shape[-2])
        return plain_forward(self, x)

    # (a forward hook would make the blocks not plain, and they would run whole)
    monkeypatch.setattr(DenseFusionBlock, "forward", counting)
    with torch.no_grad():
        net(torch.rand(1, 3, 64, 32))
    assert rows and max(rows) <= 4 + 2, rows           # a strip and its two context rows


def test_the_probe_cache_key_follows_the_strip_helpers(monkeypatch):
    # MST++'s memory per pixel is set by mstpp_lean's strips, a module defining none of
    # its layers: a cached probe of an older version would plan with stale memory
    from pathlib import Path

    from mehs.ssr import probe_cache
    from mehs.ssr.net import mstpp_lean

    net = build_network(arch="mstpp", preset="tiny")
    key = probe_cache.network_key(net)
    lean = str(Path(mstpp_lean.__file__).resolve())
    real = Path.read_bytes

    def edited(self):
        data = real(self)
        return data + b"\n# edited\n" if str(Path(self).resolve()) == lean else data

    monkeypatch.setattr(Path, "read_bytes", edited)
    assert probe_cache.network_key(net) != key


# -- what an independent review of the strips found (session 27) ---------------------------
def _mstpp(preset="tiny", **params):
    torch.manual_seed(8)
    net = build_network(arch="mstpp", preset=preset, params=params or None).eval()
    with torch.no_grad():
        for m in net.modules():
            if hasattr(m, "rescale"):
                m.rescale.fill_(4.0)
    _chunked(net, 3 * 24)
    return net


def _assert_lean_is_plain(net, x, tol=1e-5):
    lean, plain = _lean_and_plain(net, x)
    torch.testing.assert_close(lean, plain, rtol=tol, atol=tol * float(plain.abs().max()))


def test_mst_strips_never_write_into_maps_they_do_not_own():
    # an identity in place of a convolution returns its input, which the strips wrote
    # into (MST's own input, MST++'s global residual); a block subclass that keeps its
    # output (feature visualisation) had it overwritten by the decoder
    from mehs.ssr.net.mstpp2022 import MSAB

    net = _mstpp()
    net.body_stages[0].embedding = nn.Identity()
    _assert_lean_is_plain(net, torch.rand(1, 3, 24, 16) * 5)
    mst = _mstpp().body_stages[0].eval()
    x = torch.rand(1, 31, 24, 16)
    before = x.clone()
    with torch.no_grad():
        mst(x)
    assert torch.equal(x, before)

    class Keeping(MSAB):
        def forward(self, y):
            self.kept = super().forward(y)
            return self.kept

    net = _mstpp()
    stage = net.body_stages[0]
    old = stage.encoder[0][0]
    keep = Keeping(31, 31, 1, len(old.attn))
    keep.load_state_dict(old.state_dict())
    stage.encoder[0][0] = keep
    x = torch.rand(1, 3, 24, 16) * 5
    with torch.no_grad():
        net(x)
        kept = keep.kept.clone()
    net(x.clone().requires_grad_())
    torch.testing.assert_close(kept, keep.kept.detach(), rtol=1e-5, atol=1e-5)


@pytest.mark.parametrize("change", ["identity bottleneck", "biased values", "biased keys",
                                    "deeper positional term", "grouped fusion"])
def test_changed_mstpp_parts_run_as_the_plain_graph(change):
    net = _mstpp()
    stage = net.body_stages[0]
    msa = stage.encoder[0][0].attn[0]
    if change == "identity bottleneck":
        stage.bottleneck = nn.Identity()
    elif change == "biased values":
        msa.to_v = nn.Linear(31, 31, bias=True)
    elif change == "biased keys":
        msa.to_k = nn.Linear(31, 31, bias=True)
    elif change == "deeper positional term":
        msa.pos_emb.append(nn.Conv2d(31, 31, 3, 1, 1, groups=31, bias=False))
    else:
        up, fuse, block = stage.decoder[0]
        stage.decoder[0][1] = nn.Conv2d(fuse.in_channels, fuse.out_channels, 1, groups=31)
    _assert_lean_is_plain(net, torch.rand(1, 3, 24, 16) * 5)


def test_a_module_in_place_of_an_hscnnd_block_runs():
    torch.manual_seed(6)
    net = build_network(arch="hscnnd", preset="tiny").eval()
    net.blocks[1] = nn.Sequential(net.blocks[1])
    _chunked(net, 17 * 2)
    _assert_lean_is_plain(net, torch.rand(1, 3, 23, 17))


def test_a_float64_mstpp_keeps_its_precision():
    net = _mstpp().double()
    x = torch.rand(1, 3, 24, 16, dtype=torch.float64) * 5
    _assert_lean_is_plain(net, x, tol=1e-12)


def test_autocast_gives_the_plain_graphs_dtype():
    net = _mstpp()
    x = torch.rand(1, 3, 24, 16)
    with torch.autocast("cpu", dtype=torch.bfloat16):
        with torch.no_grad():
            lean = net(x)
        plain = net(x.clone().requires_grad_())
    assert lean.dtype == plain.dtype


def test_mst_refuses_a_size_off_its_grid_as_the_plain_graph_does():
    mst = _mstpp().body_stages[0].eval()
    x = torch.rand(1, 31, 9, 8)                  # one level: a multiple of 2 needed
    with pytest.raises(RuntimeError):
        mst(x.clone().requires_grad_())
    with pytest.raises(RuntimeError), torch.no_grad():
        mst(x)


@pytest.mark.parametrize("arch", ["galliani", "hscnnd", "hdrssr", "mstpp"])
def test_the_memory_probe_covers_images_of_several_strips(arch):
    # the probes' own-chunk run was exactly one chunk large, where the strip
    # convolutions run whole: images of several strips held 7.5 % more than predicted
    from mehs.ssr.tiling_probes import _peak_tensor_bytes, torch_memory_probe

    torch.manual_seed(0)
    net = build_network(arch=arch, preset="small").eval()
    model = torch_memory_probe(net)
    for side in (300, 384):
        counted, _ = _peak_tensor_bytes(net, side)
        # (to 2 %: a line through two probes and an anchor; the allocator's factor on top)
        # (HSCNN-D streams its rows: a window per column of the image, session 29)
        assert counted <= 1.02 * (model["fixed_bytes"] + model["bytes_per_pixel"] * side * side
                                  + model.get("bytes_per_column", 0.0) * side)


def _tiled_and_whole(net, side, tile):
    """A torch SSR model of ``net``: whole, then in tiles of about ``tile``² pixels."""
    from mehs.ssr.net.export import TorchSSRModel

    model = TorchSSRModel(net)
    rgb = (torch.rand(side, side - 16, 3) * 4).numpy()
    model.tiling = "off"
    whole = model.standard_spectrum(rgb)
    model.tiling = {"bytes_per_pixel": 400.0, "max_bytes": 400 * tile * tile}
    tiled = model.standard_spectrum(rgb)
    assert model._tiling_last["summary"]["tiles"] > 1
    np.testing.assert_allclose(tiled, whole, rtol=0, atol=1e-5 * np.abs(whole).max())
    return model._tiling_last["plan"]


def test_a_local_zoo_network_tiles_within_the_memory_budget(tmp_path, monkeypatch):
    # HSCNN-D ran on fixed 512² tiles whatever the memory (2.7 GB for 1024×512 under a
    # 1 GB cap) and whatever the model's tiling; it now tiles as every network does
    monkeypatch.setenv("MEHS_CACHE_DIR", str(tmp_path))
    torch.manual_seed(0)
    net = build_network(arch="hscnnd", preset="tiny").eval()
    plan = _tiled_and_whole(net, 96, 40)
    assert plan.margin >= net.receptive_radius                        # (on the grid)


def test_a_declared_radius_is_not_trusted_over_the_measured_field(tmp_path, monkeypatch):
    # a part replaced by a wider one leaves HSCNN-D's declared radius too small (5.7e-3
    # off, silently); a declaration was also cached as the architecture's margin
    monkeypatch.setenv("MEHS_CACHE_DIR", str(tmp_path))
    torch.manual_seed(0)
    net = build_network(arch="hscnnd", preset="tiny").eval()
    net.blocks[1] = nn.Conv2d(net.blocks[1].conv1.in_channels, net.fuse, 21, padding=10,
                              bias=False)
    assert _tiled_and_whole(net, 160, 72).margin >= 12


def test_probes_under_autocast_are_cached_apart():
    from mehs.ssr.probe_cache import network_key

    net = build_network(arch="hscnnd", preset="tiny")
    key = network_key(net)
    with torch.autocast("cpu", dtype=torch.bfloat16):
        assert network_key(net) != key
    assert network_key(net) == key


@pytest.mark.parametrize("declared,want", [(20, 24), (65, 72)])
def test_a_declared_radius_wider_than_measured_raises_the_margin(tmp_path, monkeypatch,
                                                                 declared, want):
    # a field probe sees only the paths its inputs open (HSCNN-D full: 24 px measured, 31
    # by construction); the declaration raises the margin, on the grid (65, the global
    # operations' marker, would have read as one), and is not cached with the probes
    from mehs.ssr.net.export import TorchSSRModel

    monkeypatch.setenv("MEHS_CACHE_DIR", str(tmp_path))
    torch.manual_seed(0)
    net = build_network(arch="hscnnd", preset="tiny").eval()
    net.receptive_radius = declared
    model = TorchSSRModel(net)
    rgb = (torch.rand(200, 200, 3) * 4).numpy()
    model.tiling = {"bytes_per_pixel": 100.0, "max_bytes": 100 * 190 * 190, "statistics": "tile"}
    with warnings.catch_warnings():
        warnings.simplefilter("error", RuntimeWarning)
        model.standard_spectrum(rgb)
    assert model._tiling_last["plan"].margin == want
    plain = build_network(arch="hscnnd", preset="tiny").eval()
    other = TorchSSRModel(plain)
    other.tiling = dict(model.tiling)
    other.standard_spectrum(rgb)
    assert other._tiling_last["plan"].margin < want


def test_a_model_converts_under_autocast():
    # under CPU bfloat16 autocast every conversion failed ("unsupported ScalarType
    # BFloat16": numpy has no bfloat16); the spectra come back as float32
    from mehs.ssr.net.export import TorchSSRModel

    torch.manual_seed(0)
    model = TorchSSRModel(build_network(arch="hdrssr", preset="tiny").eval())
    rgb = (torch.rand(64, 48, 3) * 2).numpy()
    plain = model.standard_spectrum(rgb)
    with torch.autocast("cpu", dtype=torch.bfloat16):
        low = model.standard_spectrum(rgb)
    assert low.dtype == np.float32
    # (bfloat16 keeps 8 bits of mantissa)
    np.testing.assert_allclose(low, plain, rtol=0, atol=0.1 * np.abs(plain).max())
