"""The trained networks as SSR models: registry, checkpoints, ONNX round trip (torch extra)."""

import numpy as np
import pytest

torch = pytest.importorskip("torch")
# tiny nets: a second thread only spins on a shared 2-core machine
torch.set_num_threads(1)

from mehs.errors import InputError  # noqa: E402
from mehs.rgb import WAVELENGTHS_31  # noqa: E402
from mehs.ssr.luminance import restore_luminance  # noqa: E402
from mehs.ssr.net.export import TorchSSRModel, export_onnx, load_torch_model  # noqa: E402
from mehs.ssr.net.model import NetConfig, build_network  # noqa: E402
from mehs.ssr.net.train import save_checkpoint, TrainConfig  # noqa: E402

TINY = dict(first_channels=8, down_layers=(1, 1), bottleneck_layers=1, growth=4, n_basis=4)


def _net(variant, seed=0):
    torch.manual_seed(seed)
    net = build_network(NetConfig.from_dict(dict(variant=variant, **TINY)))
    # a few BN statistics away from their defaults, so eval mode is really exercised
    net.train()
    with torch.no_grad():
        for _ in range(3):
            net(torch.rand(2, 3, 16, 16) * 5)
    return net.eval()


def _rgb(h, w, seed=0):
    rng = np.random.default_rng(seed)
    return (rng.random((h, w, 3)) * rng.uniform(0.1, 30, size=(h, w, 1))).astype(np.float32)


def _save(net, path):
    return save_checkpoint(path, net, None, None, epoch=0, train_config=TrainConfig(),
                           history=[])


@pytest.mark.parametrize("variant", ["hdrssr", "fcdensenet"])
def test_onnx_round_trip_matches_torch(tmp_path, variant):
    pytest.importorskip("onnxruntime")
    from mehs.ssr.models import load_model

    net = _net(variant)
    path = export_onnx(net, tmp_path / f"{variant}.onnx")
    model = load_model(str(path))
    ref = TorchSSRModel(net)
    for hw in [(37, 21), (16, 64), (5, 3)]:  # dynamic, odd sizes, smaller than 2**depth
        rgb = _rgb(*hw)
        got, want = model(rgb), ref(rgb)
        assert got.shape == (*hw, 31)
        np.testing.assert_allclose(got, want, rtol=2e-4, atol=1e-5 * np.abs(want).max())
    np.testing.assert_array_equal(model.wavelengths, WAVELENGTHS_31)
    import onnx
    meta = {p.key: p.value for p in onnx.load(str(path)).metadata_props}
    assert meta["mehs_variant"] == net.config.variant and meta["mehs_preprocessing"] == "reinhard"


def test_torch_luminance_restoration_equals_the_evaluation_function():
    net = _net("hdrssr")
    rgb = _rgb(9, 13, 1)
    x = torch.from_numpy(rgb.transpose(2, 0, 1)[None].copy())
    with torch.no_grad():
        S = net(x)
        S[0, :, 0, 0] = 0.0  # a zero shape takes the guarded (flat) path in both
        S[0, :, 1, 1] *= 1e-9 / float(net.xyz_sum(S)[0, 0, 1, 1])  # dim but valid: kept in both
        S[0, :, 2, 2] = -1.0  # X+Y+Z < 0: flat in both
        ours = net.restore_luminance(S, x)[0].permute(1, 2, 0).numpy()
    theirs = restore_luminance(S[0].permute(1, 2, 0).numpy(), rgb, WAVELENGTHS_31)
    np.testing.assert_allclose(ours, theirs, rtol=1e-4, atol=1e-6 * np.abs(theirs).max())


def test_registry_loads_checkpoints_by_name(tmp_path):
    from mehs.ssr.models import list_models, load_model

    assert {"hdrssr", "fcdensenet"} <= set(list_models())
    net = _net("hdrssr")
    ckpt = _save(net, tmp_path / "best.pt")
    model = load_model("hdrssr", checkpoint=str(ckpt))
    assert model.name == "hdrssr" and model.restores_luminance
    assert model.preprocessing == "reinhard"
    rgb = _rgb(11, 7)
    out = model(rgb)
    assert out.shape == (11, 7, 31) and out.dtype == np.float32
    np.testing.assert_allclose(out, load_torch_model(ckpt)(rgb), rtol=1e-6)
    by_path = load_model(str(ckpt))  # a .pt spec, as `mehs evaluate --models x.pt` gives it
    np.testing.assert_array_equal(by_path(rgb), out)
    with pytest.raises(InputError, match="predicts 31 bands"):
        load_model(str(ckpt), wavelengths=np.arange(400, 701, 5))
    with pytest.raises(InputError, match="needs a trained checkpoint"):
        load_model("hdrssr")
    with pytest.raises(InputError, match="not 'fcdensenet'"):
        load_model("fcdensenet", checkpoint=str(ckpt))


def test_model_rejects_bad_input(tmp_path):
    model = TorchSSRModel(_net("fcdensenet"))
    with pytest.raises(InputError, match=r"\(H, W, 3\)"):
        model(np.zeros((4, 4, 4), np.float32))
    bad = _rgb(4, 4)
    bad[1, 1, 0] = np.nan
    with pytest.raises(InputError, match="NaN"):
        model(bad)


def test_train_network_uses_the_architectures_recipe_by_default(monkeypatch, tmp_path):
    """The library call trains AWAN at its paper's learning-rate range, as the CLI does (it
    used the default recipe, 10× AWAN's rate)."""
    from mehs.ssr.net import train as T

    asked = []
    real = T.TrainConfig.for_arch.__func__

    def spy(cls, arch, **kw):
        asked.append(arch)
        raise KeyboardInterrupt      # enough: the recipe was chosen from the architecture

    monkeypatch.setattr(T.TrainConfig, "for_arch", classmethod(spy))
    with pytest.raises(KeyboardInterrupt):
        T.train_network([], tmp_path / "run", net_config=NetConfig(arch="awan"), progress=False)
    assert asked == ["awan"]
    assert real(T.TrainConfig, "awan").lr_max < T.TrainConfig().lr_max
