"""Audit of the SSR training protocol against the paper (§3.6.1–3.6.2) and peers' code:
resume determinism, crash-safe checkpoints, the validation metric, scene splits."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

torch = pytest.importorskip("torch")
torch.set_num_threads(1)  # tiny nets on a shared 2-core machine

from _checks import colorchecker_pair, write_mat73  # noqa: E402
from mehs.errors import FormatError, InputError  # noqa: E402
from mehs.rgb import WAVELENGTHS_31  # noqa: E402
from mehs.ssr.net.base import NetConfig  # noqa: E402
from mehs.ssr.net.train import (TrainConfig, evaluate_pairs, read_checkpoint,  # noqa: E402
                                train_network)


def _pair(h, w, seed, block=4):
    return colorchecker_pair(h, w, seed, block)


# ----------------------------------------------------------------------------- resume
def test_resumed_dropout_network_trains_exactly_as_an_uninterrupted_one(tmp_path):
    """Galliani's FC-DenseNet has dropout (p = 0.2): its masks come from torch's generator,
    which was seeded once at the start, so a resumed run replayed epoch 0's masks in epoch 1
    (weights 0.018 apart after 2 epochs). Now torch is reseeded per (seed, epoch)."""
    pairs = [_pair(24, 24, 1), _pair(24, 16, 2)]
    cfg = NetConfig(arch="galliani", preset="tiny")
    tc = TrainConfig(epochs=2, batch=2, patch=16, patches_per_image=2, seed=7)
    full = train_network(pairs, tmp_path / "full", net_config=cfg, train_config=tc,
                         progress=False)
    train_network(pairs, tmp_path / "r", net_config=cfg,
                  train_config=TrainConfig(**{**tc.__dict__, "epochs": 1}), progress=False)
    resumed = train_network(pairs, tmp_path / "r", net_config=cfg, train_config=tc,
                            resume=True, progress=False)
    assert [h["train_loss"] for h in resumed.history] == [h["train_loss"] for h in full.history]
    a, b = full.network.state_dict(), resumed.network.state_dict()
    for k in a:
        torch.testing.assert_close(a[k], b[k], rtol=0, atol=0, msg=k)


def test_run_killed_between_checkpoint_writes_keeps_best_pt_the_best(tmp_path, monkeypatch):
    """Killed after last.pt of the best epoch but before its best.pt, the old order left a
    last.pt whose history named that epoch the best while best.pt held an older epoch, and
    the resumed run never replaced it."""
    import mehs.ssr.net.train as train_mod

    pairs = [_pair(16, 16, 3)]
    cfg = NetConfig(arch="hdrssr", preset="tiny")
    tc = TrainConfig(epochs=3, batch=2, patch=16, patches_per_image=2, seed=1)
    real_save = train_mod.save_checkpoint

    def killed_at_epoch_2_best(path, *a, epoch, **k):
        if Path(path).name == "best.pt" and epoch == 2:
            raise KeyboardInterrupt  # the process dies while writing best.pt of epoch 2
        return real_save(path, *a, epoch=epoch, **k)

    monkeypatch.setattr(train_mod, "save_checkpoint", killed_at_epoch_2_best)
    with pytest.raises(KeyboardInterrupt):
        train_network(pairs, tmp_path, net_config=cfg, train_config=tc, progress=False)
    monkeypatch.setattr(train_mod, "save_checkpoint", real_save)
    res = train_network(pairs, tmp_path, net_config=cfg, train_config=tc, progress=False,
                        resume=True)
    losses = [h["train_loss"] for h in res.history]
    assert [h["epoch"] for h in res.history] == [0, 1, 2]
    assert int(np.argmin(losses)) == 2, losses  # the tiny set's loss falls every epoch
    assert read_checkpoint(tmp_path / "best.pt")["epoch"] == 2


# ----------------------------------------------------------------------------- validation
def test_validation_reports_the_papers_mrae_of_restored_spectra(tmp_path):
    """The paper reports SAM and MRAE (§3.6.3); the validation now reports both, equal to
    mehs.ssr.metrics on the luminance-restored spectra (MRAE: y ≤ 0 excluded)."""
    from mehs.ssr.metrics import mrae, sam_deg
    from mehs.ssr.net.zoo import build_network

    torch.manual_seed(0)
    net = build_network(NetConfig(arch="hdrssr", preset="tiny")).eval()
    pr = _pair(16, 12, 5)
    pr.valid[2, 3] = False
    v = evaluate_pairs(net, [pr])
    with torch.no_grad():
        spec = net.spectra(torch.from_numpy(pr.rgb.transpose(2, 0, 1)[None].copy()))
    spec = spec[0].numpy().transpose(1, 2, 0)
    assert v["mrae"] == pytest.approx(mrae(spec, pr.hs, valid=pr.valid), rel=1e-5)
    assert v["sam_deg"] == pytest.approx(sam_deg(spec, pr.hs, valid=pr.valid), rel=1e-4)
    res = train_network([_pair(16, 16, 6)], tmp_path, net_config=NetConfig(arch="hdrssr",
                        preset="tiny"), val_pairs=[pr], progress=False,
                        train_config=TrainConfig(epochs=1, batch=2, patch=16,
                                                 patches_per_image=2))
    assert np.isfinite(res.history[-1]["val_mrae"])


# ----------------------------------------------------------------------------- splits
def test_synthetic_set_never_puts_a_scene_in_two_splits(tmp_path):
    """Ratios 0 : 0.5 : 0.5 of 3 scenes rounded to 2 val + 2 test: n_train was −1 and
    ids[:-1] put a test scene into train."""
    from mehs.ssr.synthetic import make_paired_set

    out = make_paired_set(tmp_path / "ds", n_scenes=3, size=8, splits=(0, 0.5, 0.5))
    sp = json.loads((out / "manifest.json").read_text())["splits"]
    ids = [s for v in sp.values() for s in v]
    assert sorted(ids) == sorted(set(ids)) and len(ids) == 3, sp
    assert sp["train"] == []
    with pytest.raises(ValueError, match="non-negative"):
        make_paired_set(tmp_path / "bad", n_scenes=3, size=8, splits=(0, 0, 0))


def test_train_ssr_refuses_a_dataset_with_splits_but_no_train_scenes(tmp_path):
    """It trained on *all* scenes (the test scenes included) and validated on scenes it
    trained on when the train split was empty."""
    from mehs.cli.train_ssr import _splits
    from mehs.ssr.synthetic import make_paired_set

    ds = make_paired_set(tmp_path / "ds", n_scenes=3, size=8)
    m = json.loads((ds / "manifest.json").read_text())
    ids = sorted(s for v in m["splits"].values() for s in v)
    m["splits"] = {"train": [], "val": ids[:1], "test": ids[1:]}  # an evaluation-only set
    (ds / "manifest.json").write_text(json.dumps(m))
    with pytest.raises(InputError, match="no training scenes") as e:
        _splits(ds)
    assert str(ds) in str(e.value)


def test_manifest_with_a_scene_in_two_splits_is_a_format_error(tmp_path):
    from mehs.ssr.data import load_pairs
    from mehs.ssr.synthetic import make_paired_set

    ds = make_paired_set(tmp_path / "ds", n_scenes=3, size=8)
    m = json.loads((ds / "manifest.json").read_text())
    m["splits"]["test"].append(m["splits"]["train"][0])
    (ds / "manifest.json").write_text(json.dumps(m))
    with pytest.raises(FormatError, match="two splits") as e:
        load_pairs(ds, split="test")
    assert "manifest.json" in str(e.value)


def test_train_ssr_on_arad1k_validates_on_held_out_training_scenes(tmp_path, capsys):
    """Paper §3.6.1: "we used the official validation data as test data and randomly
    selected 10 data from the training data as validation data". ARAD-1K's valid_list is
    the split mehs evaluate scores (no test split); best.pt was chosen on it."""
    from mehs.cli import main

    root = tmp_path / "ARAD_1K"
    for i in range(1, 6):
        folder = "Valid" if i == 5 else "Train"
        cube = _pair(16, 16, 10 + i).hs / 40
        write_mat73(root / f"{folder}_Spec" / f"ARAD_1K_{i:04d}.mat",
                     {"cube": cube, "bands": WAVELENGTHS_31[None, :]})
    (root / "split_txt").mkdir()
    (root / "split_txt" / "train_list.txt").write_text(
        "".join(f"ARAD_1K_{i:04d}\n" for i in range(1, 5)))
    (root / "split_txt" / "valid_list.txt").write_text("ARAD_1K_0005\n")
    args = ["train-ssr", str(root), "--preset", "tiny", "--epochs", "1", "--patch", "16",
            "--patches-per-image", "2", "--batch", "2", "--quiet", "--no-onnx",
            "--val-count", "2", "--seed", "3"]
    assert main(args + ["--out", str(tmp_path / "run")]) == 0
    extra = read_checkpoint(tmp_path / "run" / "best.pt")["extra"]
    assert "ARAD_1K_0005" not in extra["val_ids"] + extra["train_ids"]
    assert len(extra["val_ids"]) == 2 and len(extra["train_ids"]) == 2
    assert not set(extra["val_ids"]) & set(extra["train_ids"])
    assert "validating on 2" in capsys.readouterr().out
    # reproducible from the seed
    assert main(args + ["--out", str(tmp_path / "run2")]) == 0
    assert read_checkpoint(tmp_path / "run2" / "best.pt")["extra"]["val_ids"] == extra["val_ids"]
