"""FC-DenseNet features read in row groups at inference (issue 16): the first convolution
computed per strip, the level-0 layers, the up-sampling and the last block stored apart,
never concatenated; the head's result written into memory it has read. Each must give
the plain training graph's numbers."""

import pytest
from _checks import peak_live_bytes

torch = pytest.importorskip("torch")
torch.set_num_threads(1)

from torch import nn  # noqa: E402
import torch.nn.functional as F  # noqa: E402

from mehs.ssr.net import build_network  # noqa: E402
from mehs.ssr.net import fcdensenet_lean  # noqa: E402
from mehs.ssr.net.strips import RowGroups  # noqa: E402


def _chunked(net, pixels):
    for m in net.modules():
        if isinstance(getattr(m, "chunk_pixels", None), int):
            m.chunk_pixels = pixels


def _trained_like(net, seed=0):
    """Batch norms with statistics and affine parameters far from their initial 0 / 1."""
    g = torch.Generator().manual_seed(seed)
    for m in net.modules():
        if isinstance(m, nn.BatchNorm2d):
            c = m.num_features
            m.running_mean.copy_(torch.rand(c, generator=g) - 0.5)
            m.running_var.copy_(0.3 + 2 * torch.rand(c, generator=g))
            if m.affine:
                m.weight.data.copy_(0.5 + torch.rand(c, generator=g))
                m.bias.data.copy_(0.4 * torch.rand(c, generator=g) - 0.2)
    return net


def _lean_and_plain(net, x):
    with torch.no_grad():
        lean = net(x)
    plain = net(x.clone().requires_grad_()).detach()
    return lean, plain


@pytest.mark.parametrize("affine", [True, False])
def test_row_groups_normalise_as_the_batch_norm_of_their_concatenation(affine):
    torch.manual_seed(1)
    stored, computed_src = torch.rand(2, 5, 9, 7), torch.rand(2, 3, 9, 7)
    computed = lambda a, b: computed_src[:, :, a:b] * 2.0  # noqa: E731
    groups = RowGroups([(3, computed), (5, stored)], stored, 9, 7)
    whole = torch.cat([computed_src * 2.0, stored], dim=1)
    bn = _trained_like(nn.BatchNorm2d(8, affine=affine)).eval()
    torch.testing.assert_close(groups.rows(2, 6), whole[:, :, 2:6], rtol=0, atol=0)
    torch.testing.assert_close(groups.normalized(bn, 2, 6), F.relu(bn(whole[:, :, 2:6])))
    torch.testing.assert_close(groups.prefix(6).whole(), whole[:, :6], rtol=0, atol=0)
    with pytest.raises(ValueError, match="computed group"):
        groups.prefix(2)
    with pytest.raises(ValueError, match="of a map of 8"):
        groups.prefix(9)
    # a batch, and a group not owned: no output buffer is handed out
    assert groups.output_buffer(3) is None


def test_an_output_buffer_is_only_an_owned_stored_group():
    a, b = torch.rand(1, 4, 5, 6), torch.rand(1, 8, 5, 6)
    assert RowGroups([(4, a), (8, b)], a, 5, 6).output_buffer(3) is None
    owned = RowGroups([(4, a), (8, b)], a, 5, 6, owned=(b,))
    buf = owned.output_buffer(6)
    assert buf.shape == (1, 6, 5, 6) and buf.data_ptr() == b.data_ptr()
    assert owned.output_buffer(9) is None               # wider than any owned group


@pytest.mark.parametrize("arch", ["hdrssr", "mikamoto", "galliani"])
@pytest.mark.parametrize("preset,n,shape,pixels", [("tiny", 1, (45, 37), 150),
                                                   ("tiny", 2, (33, 40), 90),
                                                   ("small", 1, (61, 50), 400),
                                                   ("tiny", 1, (20, 24), 0)])
def test_heads_on_row_groups_give_the_plain_graphs_numbers(arch, preset, n, shape, pixels):
    # odd sizes (the padding to the pooling grid, the crop), strips of a few rows, a
    # batch, and chunk_pixels 0 (whole maps)
    torch.manual_seed(5)
    net = _trained_like(build_network(arch=arch, preset=preset)).eval()
    _chunked(net, pixels)
    assert fcdensenet_lean.lean(net.features)
    x = torch.rand(n, 3, *shape) * 6
    lean, plain = _lean_and_plain(net, x)
    assert lean.shape == plain.shape == (n, 31, *shape)
    torch.testing.assert_close(lean, plain, rtol=1e-5, atol=1e-5 * float(plain.abs().max()))


@pytest.mark.parametrize("arch", ["hdrssr", "galliani"])
def test_the_head_writes_into_the_upsamplings_memory(arch):
    # 32 up-sampled channels hold the 31 bands (the tiny and small presets have 8 and 16:
    # their output is allocated, as FC-DenseNet56's 48 are not)
    torch.manual_seed(2)
    net = _trained_like(build_network(arch=arch, preset="tiny", growth=16, down_layers=(2, 2),
                                      bottleneck_layers=2)).eval()
    assert net.features.trans_up[-1].out_channels == 32
    _chunked(net, 200)
    for shape in [(32, 24), (29, 21)]:                 # on the grid, and cropped
        lean, plain = _lean_and_plain(net, torch.rand(1, 3, *shape))
        torch.testing.assert_close(lean, plain, rtol=1e-5, atol=1e-5 * float(plain.abs().max()))
        # the caller gets a compact result: a view would hold the up-sampling's 32
        # channels of the padded size for 31, and not be contiguous when cropped
        assert lean.is_contiguous()
        assert lean.untyped_storage().nbytes() == lean.numel() * 4


def test_a_replaced_or_hooked_galliani_head_sees_the_cropped_features():
    # the row groups are of the padded size; only a plain 1×1 head may run on them
    torch.manual_seed(7)
    net = _trained_like(build_network(arch="galliani", preset="tiny")).eval()
    x = torch.rand(1, 3, 17, 23)
    c = net.head.in_channels
    net.head = nn.Conv2d(c, 31, 3, padding=1)
    lean, plain = _lean_and_plain(net, x)
    torch.testing.assert_close(lean, plain, rtol=1e-5, atol=1e-5 * float(plain.abs().max()))

    net.head = nn.Conv2d(c, 31, 1)
    seen = []
    net.head.register_forward_hook(lambda m, i, o: seen.append(tuple(i[0].shape)))
    lean, plain = _lean_and_plain(net, x)
    assert seen == [(1, c, 17, 23)] * 2
    torch.testing.assert_close(lean, plain, rtol=1e-5, atol=1e-5 * float(plain.abs().max()))


def test_the_callers_input_is_left_as_it_was():
    torch.manual_seed(4)
    net = build_network(arch="hdrssr", preset="tiny").eval()
    _chunked(net, 120)
    x = torch.rand(1, 3, 32, 32)
    kept = x.clone()
    with torch.no_grad():
        y = net(x)
    assert torch.equal(x, kept) and y.data_ptr() != x.data_ptr()


def test_a_hooked_or_replaced_part_runs_the_plain_forward():
    torch.manual_seed(3)
    net = _trained_like(build_network(arch="hdrssr", preset="tiny")).eval()
    _chunked(net, 150)
    x = torch.rand(1, 3, 40, 36)
    seen = []
    handle = net.features.first.register_forward_hook(lambda m, i, o: seen.append(o.shape))
    assert not fcdensenet_lean.lean(net.features)
    lean, plain = _lean_and_plain(net, x)
    handle.remove()
    assert seen == [(1, 8, 40, 36)] * 2                 # the hook saw whole calls
    torch.testing.assert_close(lean, plain, rtol=1e-5, atol=1e-5 * float(plain.abs().max()))

    class Doubled(nn.Conv2d):
        def forward(self, y):
            return 2 * super().forward(y)

    old = net.features.first
    net.features.first = Doubled(old.in_channels, old.out_channels, 3, padding=1)
    net.features.first.load_state_dict(old.state_dict())
    assert not fcdensenet_lean.lean(net.features)
    lean, plain = _lean_and_plain(net, x)
    torch.testing.assert_close(lean, plain, rtol=1e-5, atol=1e-5 * float(plain.abs().max()))


def test_fc_densenet56_holds_three_full_resolution_maps_of_48_channels():
    # the last block's map was one 192-channel buffer, allocated while the 96-channel
    # skip was alive (288 channels at the peak: 2.4 GB at 2048×1024); now the level-0
    # layers', the up-sampling's and the last block's 48 channels each, the head's
    # output in the up-sampling's memory, the first convolution per strip
    torch.manual_seed(0)
    net = build_network(arch="hdrssr", preset="full").eval()
    side = 256
    _chunked(net, 2048)                # strips far smaller than the image, as on a large one
    with torch.no_grad():
        peak = peak_live_bytes(lambda: net(torch.rand(1, 3, side, side)))
    channels = peak / (side * side * 4)
    assert channels < 175, channels


@pytest.mark.parametrize("arch", ["hdrssr", "galliani"])
@pytest.mark.parametrize("how", ["input", "network"])
def test_channels_last_inputs_and_networks_give_the_plain_numbers(arch, how):
    # an HWC image seen as NCHW has channels-last strides, and so has the per-strip first
    # convolution of it: torch's batch norm wrote that layout into the NCHW strip
    torch.manual_seed(8)
    net = _trained_like(build_network(arch=arch, preset="tiny")).eval()
    _chunked(net, 150)
    x = torch.rand(1, 13, 21, 3).permute(0, 3, 1, 2) * 4
    if how == "network":
        net = net.to(memory_format=torch.channels_last)
        x = x.contiguous()
    lean, plain = _lean_and_plain(net, x)
    torch.testing.assert_close(lean, plain, rtol=1e-5, atol=1e-5 * float(plain.abs().max()))


def test_a_bfloat16_network_with_float32_batch_norms_runs():
    torch.manual_seed(9)
    net = _trained_like(build_network(arch="hdrssr", preset="tiny")).eval().bfloat16()
    for m in net.modules():
        if isinstance(m, nn.BatchNorm2d):
            m.float()
    _chunked(net, 150)
    x = (torch.rand(1, 3, 16, 16) * 4).bfloat16()
    lean, plain = _lean_and_plain(net, x)
    assert lean.dtype == plain.dtype == torch.bfloat16
    torch.testing.assert_close(lean.float(), plain.float(), rtol=2e-2,
                               atol=2e-2 * float(plain.float().abs().max()))


@pytest.mark.parametrize("arch", ["galliani", "hdrssr"])
def test_an_image_of_one_strip_holds_no_second_output_or_feature_copy(arch):
    # one strip: the head's result is the output (not copied into another of its size)
    # and the features are concatenated once, for that strip (counted here: 536 and 1716
    # B/px before the row groups, 696 and 1908 with a copied output and a strip of the
    # features next to a whole-image one)
    torch.manual_seed(0)
    net = build_network(arch=arch, preset="small").eval()
    side = 96
    with torch.no_grad():
        per_pixel = peak_live_bytes(lambda: net(torch.rand(1, 3, side, side))) / side ** 2
    assert per_pixel < {"galliani": 650, "hdrssr": 1850}[arch], per_pixel


def test_probes_of_a_network_in_training_mode_are_cached_apart():
    # its batch norms use batch statistics and take no strips: the full paper network's
    # memory probe gives twice the eval figure, which must not be read for eval runs
    from mehs.ssr.probe_cache import network_key

    net = build_network(arch="hdrssr", preset="tiny").eval()
    key = network_key(net)
    net.features.down_blocks[0].layers[0][0].train()
    assert network_key(net) != key
    net.eval()
    assert network_key(net) == key
