"""Basis functions, channel attention and shapes of the SSR networks (torch extra)."""

import numpy as np
import pytest

torch = pytest.importorskip("torch")
# tiny nets: a second thread only spins on a shared 2-core machine
torch.set_num_threads(1)

from mehs.ssr.net import (ChannelAttention, FCDenseNet, MexicanHatBranch,  # noqa: E402
                          SigmoidBasisBranch, build_network, mexican_hat_basis,
                          normalise_wavelengths, sigmoid_basis, sigmoid_Jakob2019)
from mehs.ssr.net.basis import MIN_HAT_WIDTH  # noqa: E402
from mehs.rgb import WAVELENGTHS_31, cmfs_matrix  # noqa: E402

TINY = dict(first_channels=8, down_layers=(1, 1), bottleneck_layers=1, growth=4, n_basis=3)


def test_wavelengths_normalised_to_unit_interval():
    lam = normalise_wavelengths(WAVELENGTHS_31)
    assert lam[0] == 0.0 and lam[-1] == 1.0
    np.testing.assert_allclose(np.diff(lam), 1 / 30)


def test_sigmoid_matches_formula_and_limits():
    x = torch.tensor([-1e6, -3.0, -0.5, 0.0, 0.5, 3.0, 1e6], dtype=torch.float64)
    expect = 0.5 + x.numpy() / (2 * np.sqrt(1 + x.numpy() ** 2))
    np.testing.assert_allclose(sigmoid_Jakob2019(x).numpy(), expect, rtol=1e-12)
    assert sigmoid_Jakob2019(torch.tensor(0.0)) == 0.5
    assert abs(float(sigmoid_Jakob2019(x)[0])) < 1e-9 and abs(float(sigmoid_Jakob2019(x)[-1]) - 1) < 1e-9


def test_sigmoid_basis_matches_formula():
    rng = np.random.default_rng(1)
    lam = normalise_wavelengths(WAVELENGTHS_31)
    c0, c1, c2 = rng.normal(scale=5, size=3)
    got = sigmoid_basis(torch.tensor(lam), *(torch.tensor(v) for v in (c0, c1, c2))).numpy()
    x = c0 * lam ** 2 + c1 * lam + c2
    np.testing.assert_allclose(got, 0.5 + x / (2 * np.sqrt(1 + x * x)), rtol=1e-12)


def test_mexican_hat_matches_formula():
    lam = normalise_wavelengths(WAVELENGTHS_31)
    a, c = 0.15, 0.4
    t = lambda v: torch.tensor(v, dtype=torch.float64)  # noqa: E731
    got = mexican_hat_basis(t(lam), t(a), t(c)).numpy()
    u = (lam - c) / a
    np.testing.assert_allclose(got, (1 / np.sqrt(a)) * (1 - 2 * u ** 2) * np.exp(-u ** 2),
                               rtol=1e-12)
    # peak 1/√a at the centre, zero crossings at λ = c ± a/√2
    assert float(mexican_hat_basis(t(c), t(a), t(c))) == pytest.approx(1 / np.sqrt(a), rel=1e-12)
    assert float(mexican_hat_basis(t(c + a / np.sqrt(2)), t(a), t(c))) == pytest.approx(0, abs=1e-12)


@pytest.mark.parametrize("branch_cls", [SigmoidBasisBranch, MexicanHatBranch])
def test_branch_evaluates_weighted_sum_of_its_basis(branch_cls):
    torch.manual_seed(0)
    n = 4
    br = branch_cls(5, WAVELENGTHS_31, n_basis=n).double()
    feats = torch.randn(2, 5, 3, 4, dtype=torch.float64)
    out = br(feats)
    assert out.shape == (2, 31, 3, 4)
    p = br.head(feats).detach().numpy()
    lam = br.lam.numpy()  # the float32-rounded grid the branch holds, (1, 31, 1, 1)
    w = p[:, :n]
    expect = np.zeros(out.shape)
    for i in range(n):
        if branch_cls is SigmoidBasisBranch:
            c0, c1, c2 = (p[:, n + k * n + i][:, None] for k in range(3))
            x = c0 * lam ** 2 + c1 * lam + c2
            f = 0.5 + x / (2 * np.sqrt(1 + x * x))
        else:
            a = MIN_HAT_WIDTH + np.log1p(np.exp(p[:, n + i][:, None]))
            c = 1 / (1 + np.exp(-p[:, 2 * n + i][:, None]))
            u = (lam - c) / a
            f = (1 - 2 * u ** 2) * np.exp(-u ** 2) / np.sqrt(a)
        expect += w[:, i][:, None] * f
    np.testing.assert_allclose(out.detach().numpy(), expect, rtol=1e-9, atol=1e-12)


def test_channel_attention_zero_init_scales_by_exactly_one_half():
    torch.manual_seed(0)
    ca = ChannelAttention(16, reduction=4, zero_init=True)
    assert ca.squeeze.out_channels == 4
    x = torch.randn(2, 16, 7, 5)
    # sigmoid(0) = 0.5 exactly in float32, so the block is an exact ×0.5 scaling
    assert torch.equal(ca(x), x * 0.5)


def test_channel_attention_rescales_per_channel_only():
    torch.manual_seed(0)
    ca = ChannelAttention(8)
    x = torch.rand(1, 8, 6, 6) + 0.1
    with torch.no_grad():
        ratio = ca(x) / x
    # one factor per (image, channel), in (0, 1)
    assert torch.allclose(ratio, ratio[..., :1, :1].expand_as(ratio), atol=1e-6)
    assert float(ratio.min()) > 0 and float(ratio.max()) < 1
    assert not torch.allclose(ratio, torch.full_like(ratio, 0.5))


@pytest.mark.parametrize("hw", [(1, 1), (5, 3), (17, 31), (32, 16), (33, 9)])
def test_feature_extractor_handles_any_size(hw):
    net = FCDenseNet(3, first_channels=8, down_layers=(1, 1, 1), bottleneck_layers=1, growth=4).eval()
    out = net(torch.rand(2, 3, *hw))
    assert out.shape == (2, net.out_channels, *hw)
    assert torch.isfinite(out).all()


@pytest.mark.parametrize("variant", ["hdrssr", "fcdensenet"])
@pytest.mark.parametrize("hw", [(7, 13), (16, 16), (25, 1)])
def test_networks_output_31_bands_for_odd_sizes(variant, hw):
    torch.manual_seed(0)
    net = build_network(variant=variant, **TINY).eval()
    with torch.no_grad():
        rgb = torch.rand(1, 3, *hw) * 10
        out = net.spectra(rgb)
    assert out.shape == (1, 31, *hw)
    assert torch.isfinite(out).all()


def test_hdrssr_restored_output_carries_input_luminance():
    torch.manual_seed(0)
    net = build_network(variant="hdrssr", **TINY).eval()
    rgb = torch.rand(1, 3, 9, 11) * 50 + 0.1
    with torch.no_grad():
        hs = net.spectra(rgb).numpy()[0].transpose(1, 2, 0)
    M = cmfs_matrix(WAVELENGTHS_31)
    from mehs.rgb import linear_sRGB_to_XYZ
    np.testing.assert_allclose((hs @ M).sum(-1),
                               linear_sRGB_to_XYZ(rgb.numpy()[0].transpose(1, 2, 0)).sum(-1),
                               rtol=1e-4)


def test_reinhard_switch_changes_what_the_features_see():
    torch.manual_seed(0)
    a = build_network(variant="fcdensenet", reinhard=True, **TINY).eval()
    b = build_network(variant="fcdensenet", reinhard=False, **TINY).eval()
    b.load_state_dict(a.state_dict())
    x = torch.rand(1, 3, 8, 8) * 100
    assert torch.allclose(a.preprocess(x), x / (1 + x))
    assert torch.equal(b.preprocess(x), x)
    with torch.no_grad():
        assert not torch.allclose(a(x), b(x))


def test_unknown_variant_is_an_input_error():
    from mehs.errors import InputError
    with pytest.raises(InputError, match="unknown network variant"):
        build_network(variant="unet")


@pytest.mark.parametrize("branch_cls", [SigmoidBasisBranch, MexicanHatBranch])
def test_branch_row_strips_give_the_same_result(branch_cls):
    torch.manual_seed(0)
    br = branch_cls(6, WAVELENGTHS_31, n_basis=5).eval()
    feats = torch.randn(2, 6, 23, 9)
    with torch.no_grad():
        br.chunk_pixels = 0
        whole = br(feats)
        br.chunk_pixels = 40  # 40 // (2·9) = 2 rows per strip, 12 strips, the last 1 row
        strips = br(feats)
    # equal up to float32 rounding (the 1×1 conv blocks its sums differently per shape)
    torch.testing.assert_close(strips, whole, rtol=1e-5, atol=1e-5)


@pytest.mark.parametrize("arch", ["hdrssr", "mikamoto", "galliani"])
@pytest.mark.parametrize("n", [1, 2])
def test_inference_buffers_give_the_training_graphs_numbers(arch, n):
    # without autograd the dense blocks write into one preallocated tensor and the
    # head frees the features before its fusion (issue 16); with autograd the plain
    # concatenating graph runs: both must give the same numbers, also for N > 1 where
    # the buffer's channel slices are not contiguous
    from mehs.ssr.net.zoo import build_network as build_arch

    torch.manual_seed(1)
    net = build_arch(arch=arch, preset="tiny").eval()
    rgb = torch.rand(n, 3, 13, 21) * 20
    with torch.no_grad():
        lean = net(rgb)
    plain = net(rgb.requires_grad_())
    assert plain.requires_grad
    torch.testing.assert_close(lean, plain.detach(), rtol=0, atol=0)
