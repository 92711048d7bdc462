"""Training of the SSR networks: overfitting a tiny set, checkpoints, resume (torch extra)."""

import json

import numpy as np
import pytest

torch = pytest.importorskip("torch")
# tiny nets: a second thread only spins on a shared 2-core machine
torch.set_num_threads(1)

from _checks import colorchecker_pair  # noqa: E402
from mehs.errors import FormatError, InputError  # noqa: E402
from mehs.ssr.net.model import NetConfig, build_network  # noqa: E402
from mehs.ssr.net.train import (TrainConfig, TrainingPair, augment_patch,  # noqa: E402
                                evaluate_pairs, load_network, read_checkpoint,
                                sample_batch, train_network)

TINY = dict(first_channels=8, down_layers=(1, 1), bottleneck_layers=1, growth=8, n_basis=10)


# The end-to-end variant must also learn the absolute scale (a 40× brightness range
# here), so it needs more steps for the same 10× drop.
@pytest.mark.parametrize("variant,epochs", [("hdrssr", 40), ("fcdensenet", 80)])
def test_tiny_network_overfits_a_tiny_set(tmp_path, variant, epochs):
    pairs = [colorchecker_pair(32, 32, 0)]
    cfg = NetConfig.from_dict(dict(variant=variant, **TINY))
    torch.manual_seed(0)
    before = evaluate_pairs(build_network(cfg), pairs)["loss"]
    res = train_network(pairs, tmp_path, net_config=cfg, progress=False,
                        train_config=TrainConfig(epochs=epochs, batch=4, patch=32,
                                                 patches_per_image=8, seed=0))
    after = evaluate_pairs(res.network, pairs)["loss"]
    assert after < before / 10, (before, after)
    assert len(res.history) == epochs
    # the recipe's schedule: η_max at the start, warm restart at T0 = 20 epochs
    lrs = [h["lr"] for h in res.history]
    assert lrs[0] < 0.002 and lrs[19] == pytest.approx(0.002) and min(lrs) >= 1e-4 - 1e-12


def test_checkpoints_resume_and_determinism(tmp_path):
    pairs = [colorchecker_pair(24, 24, 1), colorchecker_pair(24, 16, 2)]
    val = [colorchecker_pair(16, 24, 3)]
    cfg = NetConfig.from_dict(dict(variant="hdrssr", **TINY))
    tc = TrainConfig(epochs=4, batch=2, patch=16, patches_per_image=2, seed=7)
    full = train_network(pairs, tmp_path / "full", net_config=cfg, train_config=tc,
                         val_pairs=val, progress=False)
    half = train_network(pairs, tmp_path / "resumed", net_config=cfg,
                         train_config=TrainConfig(**{**tc.__dict__, "epochs": 2}),
                         val_pairs=val, progress=False)
    assert len(half.history) == 2
    with pytest.raises(InputError, match="--resume"):
        train_network(pairs, tmp_path / "resumed", net_config=cfg, train_config=tc,
                      progress=False)
    resumed = train_network(pairs, tmp_path / "resumed", net_config=cfg, train_config=tc,
                            val_pairs=val, resume=True, progress=False)
    assert [h["epoch"] for h in resumed.history] == [0, 1, 2, 3]
    a = full.network.state_dict()
    b = resumed.network.state_dict()
    for k in a:
        torch.testing.assert_close(a[k], b[k], rtol=1e-5, atol=1e-6, msg=k)
    st = read_checkpoint(tmp_path / "full" / "last.pt")
    assert st["epoch"] == 3 and st["variant"] == "hdrssr"
    assert (tmp_path / "full" / "best.pt").exists()
    hist = json.loads((tmp_path / "full" / "history.json").read_text())
    assert len(hist) == 4 and "val_sam_deg" in hist[-1]
    assert not list((tmp_path / "full").glob("*.part*"))  # atomic writes left no temp file
    net, _ = load_network(tmp_path / "full" / "last.pt")
    x = torch.from_numpy(val[0].rgb.transpose(2, 0, 1)[None].copy())
    with torch.no_grad():
        torch.testing.assert_close(net(x), full.network.eval()(x))


def test_bad_checkpoints_and_inputs_raise_clear_errors(tmp_path):
    with pytest.raises(InputError, match="not found"):
        read_checkpoint(tmp_path / "nope.pt")
    junk = tmp_path / "junk.pt"
    junk.write_bytes(b"not a checkpoint")
    with pytest.raises(FormatError, match="junk.pt"):
        read_checkpoint(junk)
    other = tmp_path / "other.pt"
    torch.save({"weights": torch.zeros(2)}, other)
    with pytest.raises(FormatError, match="not a mehs SSR network checkpoint"):
        read_checkpoint(other)
    pr = colorchecker_pair(16, 16, 0)
    with pytest.raises(InputError, match="bands"):
        train_network([TrainingPair(pr.rgb, pr.hs[..., :30])], tmp_path / "x", progress=False)
    with pytest.raises(InputError, match="CUDA|device"):
        train_network([pr], tmp_path / "y", progress=False,
                      train_config=TrainConfig(epochs=1, device="cuda:7")
                      if not torch.cuda.is_available() else TrainConfig(device="nonsense"))
    with pytest.raises(InputError, match="does not match"):
        TrainingPair(pr.rgb, pr.hs[:8])


def test_nan_pixels_are_masked_not_learned():
    pr = colorchecker_pair(16, 16, 0)
    pr.hs[3, 4, 5] = np.nan
    p2 = TrainingPair(pr.rgb, pr.hs)
    assert not p2.valid[3, 4] and p2.valid.sum() == 255
    assert np.isfinite(p2.hs).all()


def test_augmentation_keeps_pairs_aligned():
    rng = np.random.default_rng(0)
    rgb = rng.random((6, 6, 3)).astype(np.float32)
    hs = np.concatenate([rgb, rgb], axis=-1)
    valid = rgb[..., 0] > 0.5
    seen = set()
    for _ in range(40):
        r, s, v = augment_patch(rgb, hs, valid, rng)
        np.testing.assert_array_equal(s[..., :3], r)
        np.testing.assert_array_equal(v, r[..., 0] > 0.5)
        seen.add(r.tobytes())
    assert len(seen) > 4  # flips and rotations actually happen
    pairs = [TrainingPair(rgb, hs)]
    x, y, m = sample_batch(pairs, 3, 4, np.random.default_rng(1))
    assert x.shape == (3, 3, 4, 4) and y.shape == (3, 6, 4, 4) and m.shape == (3, 1, 4, 4)
    assert m.dtype == torch.bool


def test_mrae_loss_is_ntires_and_selectable():
    """``TrainConfig(loss="mrae")``: |ŷ − y| / y over valid elements with y > 0 (NTIRE's MRAE,
    MST++'s training loss), computed here against numpy; unknown names are refused."""
    from mehs.ssr.net.base import masked_mrae

    rng = np.random.default_rng(0)
    y = rng.uniform(0.1, 1, (2, 31, 5, 4)).astype(np.float32)
    y[0, 3, 1, 1] = 0.0                                   # excluded, not a division by 0
    p = y + rng.normal(0, 0.05, y.shape).astype(np.float32)
    valid = np.ones((2, 1, 5, 4), bool)
    valid[1, 0, 2, :] = False
    got = float(masked_mrae(torch.from_numpy(p), torch.from_numpy(y), torch.from_numpy(valid)))
    m = np.broadcast_to(valid, y.shape) & (y > 0)
    assert got == pytest.approx(float(np.mean(np.abs(p - y)[m] / y[m])), rel=1e-5)
    assert TrainConfig(loss="mrae").loss == "mrae"
    with pytest.raises(InputError, match="loss"):
        TrainConfig(loss="l1")
    net = build_network(NetConfig.from_dict(dict(variant="hdrssr", **TINY)))
    with pytest.raises(InputError, match="unknown loss"):
        net.loss(torch.zeros(1, 31, 4, 4), torch.ones(1, 31, 4, 4), kind="huber")


def test_resume_on_other_scenes_is_refused(tmp_path):
    """A resumed run continues the schedule and history of its checkpoint's training set:
    other scenes (another split, dataset or hold-out seed) are refused, not mixed in."""
    cfg = NetConfig.from_dict(dict(variant="hdrssr", **TINY))
    tc = TrainConfig(epochs=1, batch=2, patch=16, patches_per_image=2, seed=0)
    pairs = [colorchecker_pair(16, 16, 1), colorchecker_pair(16, 16, 2)]
    train_network(pairs, tmp_path, net_config=cfg, train_config=tc, progress=False)
    tc2 = TrainConfig(epochs=2, batch=2, patch=16, patches_per_image=2, seed=0)
    with pytest.raises(InputError, match="other scenes"):
        train_network([pairs[0], colorchecker_pair(16, 16, 3)], tmp_path, net_config=cfg,
                      train_config=tc2, resume=True, progress=False)
    res = train_network(pairs, tmp_path, net_config=cfg, train_config=tc2, resume=True,
                        progress=False)
    assert len(res.history) == 2
