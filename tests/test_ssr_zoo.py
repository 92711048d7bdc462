"""The SSR network zoo: published sizes, shapes, both learning modes, one training step,
the AWAN non-local block against its explicit formula, exact tiling (torch extra)."""

import numpy as np
import pytest

torch = pytest.importorskip("torch")
torch.set_num_threads(1)  # small nets: a second thread only spins on a shared 2-core machine

from mehs.errors import FormatError, InputError  # noqa: E402
from mehs.ssr.net.base import NetConfig, count_parameters  # noqa: E402
from mehs.ssr.net.zoo import ARCHITECTURES, build_network, format_parameter_table  # noqa: E402

ARCHS = sorted(ARCHITECTURES)

# Published parameter counts of the full presets (31 output bands), stated here from
# the papers rather than read back from the zoo.
PUBLISHED = {
    "mstpp": 1.62e6,   # Cai et al. 2022, MST++ Table 1
    "awan": 4.04e6,    # as the MST++ paper lists AWAN
    "hscnnd": 4.65e6,  # as the MST++ paper lists HSCNN+ (HSCNN-D, 30 dense fusion blocks)
    "galliani": 1.5e6,  # Jégou et al. 2017: FC-DenseNet56
}


@pytest.mark.parametrize("arch", sorted(PUBLISHED))
def test_full_presets_have_the_published_parameter_counts(arch):
    n = count_parameters(ARCHITECTURES[arch]("full"))
    assert abs(n / PUBLISHED[arch] - 1) <= 0.10, (arch, n)


def test_paper_family_full_presets_share_one_backbone():
    # ours = Mikamoto + channel attention; Galliani = the same FC-DenseNet with a 1×1 head
    ours, mika, gal = (ARCHITECTURES[a]("full") for a in ("hdrssr", "mikamoto", "galliani"))
    assert not any("excite" in k for k in mika.state_dict())
    assert any("excite" in k for k in ours.state_dict())
    assert any(isinstance(m, torch.nn.Dropout) for m in mika.modules())
    assert not any(isinstance(m, torch.nn.Dropout) for m in ours.modules())
    assert mika.features.out_channels == gal.features.out_channels == ours.features.out_channels
    assert 0 < count_parameters(ours) - count_parameters(mika) < 0.01 * count_parameters(mika)


def test_parameter_table_lists_every_architecture():
    table = format_parameter_table()
    for arch in ARCHS:
        assert f"| {arch} |" in table


@pytest.mark.parametrize("arch", ARCHS)
@pytest.mark.parametrize("mode", ["similarity", "e2e"])
def test_small_presets_map_rgb_to_31_bands(arch, mode):
    torch.manual_seed(0)
    net = ARCHITECTURES[arch]("small", mode=mode).eval()
    rgb = torch.rand(2, 3, 13, 18) * 20 + 0.05
    with torch.no_grad():
        raw = net(rgb)
        hs = net.spectra(rgb)
    assert raw.shape == hs.shape == (2, 31, 13, 18)
    assert torch.isfinite(hs).all()
    if mode == "e2e":
        assert torch.equal(raw, hs)  # end to end: nothing is restored
    else:
        # restored spectra carry the input's X+Y+Z wherever the shape has signal
        ok = net.xyz_sum(raw) > 1e-3
        np.testing.assert_allclose(net.xyz_sum(hs)[ok].numpy(), net.rgb_xyz_sum(rgb)[ok].numpy(),
                                   rtol=1e-3)


@pytest.mark.parametrize("arch", ARCHS)
def test_one_training_step_decreases_the_loss(arch):
    torch.manual_seed(1)
    net = ARCHITECTURES[arch]("small").train()
    rgb = torch.rand(2, 3, 16, 16) * 5
    hs = torch.rand(2, 31, 16, 16) * 3 + 0.1
    opt = torch.optim.Adam(net.parameters(), lr=1e-4)

    def loss():
        torch.manual_seed(7)  # the same dropout masks before and after the step
        return net.loss(net(rgb), hs)

    before = loss()
    opt.zero_grad()
    before.backward()
    opt.step()
    with torch.no_grad():
        after = loss()
    before = float(before.detach())
    assert float(after) < before, (arch, before, float(after))


def test_awan_non_local_equals_the_explicit_second_order_formula():
    from mehs.ssr.net.awan2020 import SecondOrderNonLocal

    torch.manual_seed(0)
    blk = SecondOrderNonLocal(31)
    torch.nn.init.normal_(blk.W.weight)  # zero-initialised in the network: make it count
    x = torch.randn(2, 31, 6, 5)
    with torch.no_grad():
        th = blk.theta(x).flatten(2).transpose(1, 2)  # (n, hw, c')
        g = blk.g(x).flatten(2).transpose(1, 2)
        m = th.shape[2]
        f = (th - th.mean(2, keepdim=True)) @ th.transpose(1, 2) / m  # (n, hw, hw)
        y = torch.softmax(f, dim=-1) @ g
        want = x + blk.W(y.transpose(1, 2).reshape(2, m, 6, 5))
        torch.testing.assert_close(blk(x), want, rtol=1e-5, atol=1e-5)


def test_mst_spectral_attention_is_over_channels_and_linear_in_pixels():
    from mehs.ssr.net.mstpp2022 import SpectralMSA

    torch.manual_seed(0)
    msa = SpectralMSA(31, 31, 1)
    x = torch.randn(1, 4, 6, 31)
    with torch.no_grad():
        out = msa(x)
        # explicit: A = softmax(σ K̂ Q̂ᵀ) over the 31×31 channel similarity
        t = x.reshape(1, 24, 31)
        q = torch.nn.functional.normalize(msa.to_q(t).transpose(1, 2), dim=-1)
        k = torch.nn.functional.normalize(msa.to_k(t).transpose(1, 2), dim=-1)
        v_in = msa.to_v(t)
        a = torch.softmax(k @ q.transpose(1, 2) * msa.rescale[0], dim=-1)
        want = msa.proj((a @ v_in.transpose(1, 2)).transpose(1, 2)).view(1, 4, 6, 31)
        want = want + msa.pos_emb(v_in.reshape(1, 4, 6, 31).permute(0, 3, 1, 2)).permute(0, 2, 3, 1)
    torch.testing.assert_close(out, want, rtol=1e-5, atol=1e-5)


def test_hscnnd_tiled_inference_is_exact_and_whole_image_nets_are_not_tiled():
    from mehs.ssr.net.infer import predict_tiled

    torch.manual_seed(0)
    net = ARCHITECTURES["hscnnd"]("tiny", mode="e2e").eval()
    x = torch.rand(1, 3, 41, 37)
    with torch.no_grad():
        torch.testing.assert_close(predict_tiled(net, x, tile=12), net.spectra(x),
                                   rtol=1e-5, atol=1e-6)
    mst = ARCHITECTURES["mstpp"]("tiny", mode="e2e").eval()
    assert mst.receptive_radius is None  # spectral attention sums over every pixel
    with torch.no_grad():
        torch.testing.assert_close(predict_tiled(mst, x, tile=12), mst.spectra(x))


def test_config_records_the_trained_setting_and_round_trips():
    net = ARCHITECTURES["awan"]("tiny", mode="e2e", reinhard=True, reinhard_scale=100.0,
                                input="ldr", params={"channels": 8})
    assert net.trained_input() == {"arch": "awan", "preset": "tiny", "mode": "e2e",
                                   "input": "ldr", "preprocessing": "reinhard",
                                   "reinhard_scale": 100.0, "restores_luminance": False}
    x = torch.full((1, 3, 2, 2), 300.0)
    torch.testing.assert_close(net.preprocess(x), torch.full_like(x, 0.75))
    again = build_network(NetConfig.from_dict(net.config.to_dict()))
    assert again.config == net.config
    assert count_parameters(again) == count_parameters(net)


def test_format_1_checkpoints_still_load(tmp_path):
    from mehs.ssr.net.train import load_network

    old = {"variant": "fcdensenet", "wavelengths": list(range(400, 701, 10)),
           "first_channels": 8, "down_layers": [1, 1], "bottleneck_layers": 1, "growth": 4,
           "reduction": 4, "n_basis": 10, "reinhard": True}
    net = build_network(NetConfig.from_dict(old))
    assert (net.config.arch, net.config.mode) == ("galliani", "e2e")
    torch.save({"format": "mehs-ssr-net/1", "net_config": old, "model": net.state_dict(),
                "epoch": 0, "history": []}, tmp_path / "old.pt")
    loaded, _ = load_network(tmp_path / "old.pt")
    for k, v in net.state_dict().items():
        assert torch.equal(loaded.state_dict()[k], v), k
    torch.save({"format": "mehs-ssr-net/2", "net_config": {"arch": "unet"}, "model": {}},
               tmp_path / "bad.pt")
    with pytest.raises(FormatError, match="unet"):
        load_network(tmp_path / "bad.pt")


@pytest.mark.parametrize("kwargs, msg", [
    (dict(arch="unet"), "unknown network architecture 'unet'.*mstpp"),
    (dict(arch="awan", params={"growth": 4}), r"no parameter\(s\) \['growth'\]"),
    (dict(arch="hscnnd", params={"n_blocks": 0}), "n_blocks must be a positive whole number"),
    (dict(arch="mikamoto", params={"growth": 4.5}), "growth must be a positive whole number"),
    (dict(arch="galliani", params={"dropout": 1.5}), "dropout"),
    (dict(arch="mstpp", preset="huge"), "no preset 'huge'"),
    (dict(arch="mstpp", mode="mse"), "learning mode"),
    (dict(arch="mstpp", reinhard_scale=0.0), "reinhard_scale"),
])
def test_bad_configurations_are_named_input_errors(kwargs, msg):
    with pytest.raises(InputError, match=msg):
        build_network(NetConfig(**kwargs))


def test_train_ssr_cli_refuses_a_bad_param_before_reading_data(tmp_path, capsys):
    from mehs.cli import main

    assert main(["train-ssr", str(tmp_path / "nowhere"), "--out", str(tmp_path / "o"),
                 "--arch", "mstpp", "--param", "growth=4"]) == 2
    assert "growth" in capsys.readouterr().err
    assert main(["train-ssr", str(tmp_path / "nowhere"), "--out", str(tmp_path / "o"),
                 "--arch", "mstpp", "--param", "stages"]) == 2
    assert "KEY=VALUE" in capsys.readouterr().err


@pytest.mark.parametrize("arch", ARCHS)
def test_every_architecture_trains_with_the_one_recipe_and_reloads(arch, tmp_path):
    from mehs.ssr.net.train import TrainConfig, TrainingPair, load_network, train_network

    rng = np.random.default_rng(0)
    hs = rng.uniform(0.05, 2.0, (20, 18, 31)).astype(np.float32)
    rgb = rng.uniform(0.05, 3.0, (20, 18, 3)).astype(np.float32)
    cfg = NetConfig(arch=arch, preset="tiny", mode="e2e" if arch == "awan" else "similarity")
    tc = TrainConfig.for_arch(arch, epochs=1, batch=2, patch=12, patches_per_image=2)
    if arch == "awan":
        assert (tc.lr_max, tc.lr_min) == (2e-4, 1e-5)  # the paper's AWAN range
    res = train_network([TrainingPair(rgb, hs)], tmp_path, net_config=cfg, train_config=tc,
                        progress=False)
    assert np.isfinite(res.history[0]["train_loss"])
    net, state = load_network(res.last_checkpoint)
    assert (state["arch"], state["preset"], state["mode"]) == (arch, "tiny", cfg.mode)
    x = torch.from_numpy(rgb.transpose(2, 0, 1)[None].copy())
    with torch.no_grad():
        torch.testing.assert_close(net.spectra(x), res.network.eval().spectra(x))
