"""`mehs train-ssr` end to end on a tiny simulated ME HS set, then the models it made (torch extra)."""

import json

import numpy as np
import pytest

torch = pytest.importorskip("torch")
# tiny nets: a second thread only spins on a shared 2-core machine
torch.set_num_threads(1)

from mehs.cli import main  # noqa: E402


@pytest.fixture(scope="module")
def tiny_set(tmp_path_factory):
    from mehs.ssr.synthetic import make_paired_set

    return make_paired_set(tmp_path_factory.mktemp("set") / "ds", n_scenes=4, size=24, seed=3)


def test_train_ssr_trains_resumes_and_exports(tiny_set, tmp_path, capsys):
    out = tmp_path / "run"
    base = [str(tiny_set), "--out", str(out), "--preset", "tiny", "--patch", "16", "--batch", "2",
            "--patches-per-image", "2", "--quiet", "--seed", "1"]
    assert main(["train-ssr", *base, "--epochs", "2", "--no-onnx"]) == 0
    assert not (out / "model.onnx").exists()
    # a second run into the same folder must not silently restart it
    assert main(["train-ssr", *base, "--epochs", "3"]) == 2
    assert "--resume" in capsys.readouterr().err
    assert main(["train-ssr", *base, "--epochs", "3", "--resume"]) == 0
    hist = json.loads((out / "history.json").read_text())
    assert [h["epoch"] for h in hist] == [0, 1, 2]
    assert all(np.isfinite(h["train_loss"]) and np.isfinite(h["val_loss"]) for h in hist)
    cfg = json.loads((out / "config.json").read_text())
    assert cfg["net_config"]["arch"] == "hdrssr" and cfg["extra"]["train_split"] == "train"
    assert cfg["net_config"]["mode"] == "similarity" and cfg["net_config"]["preset"] == "tiny"

    from mehs.ssr.data import load_pairs
    from mehs.ssr.models import load_model

    pair = load_pairs(tiny_set, split="test")[0]
    rgb = pair.hdr_rgb()
    by_ckpt = load_model("hdrssr", checkpoint=str(out / "best.pt"))(rgb)
    pytest.importorskip("onnxruntime")
    by_onnx = load_model(str(out / "model.onnx"))(rgb)
    assert by_onnx.shape == rgb.shape[:2] + (31,)
    np.testing.assert_allclose(by_onnx, by_ckpt, rtol=1e-3, atol=1e-5 * np.abs(by_ckpt).max())


def test_train_ssr_end_to_end_variant_on_ldr_input(tiny_set, tmp_path):
    out = tmp_path / "e2e"
    assert main(["train-ssr", str(tiny_set), "--out", str(out), "--arch", "galliani",
                 "--mode", "e2e", "--input", "ldr", "--no-reinhard", "--preset", "tiny",
                 "--param", "growth=4", "--epochs", "1",
                 "--patch", "16", "--batch", "2", "--patches-per-image", "1", "--quiet",
                 "--no-onnx"]) == 0
    from mehs.ssr.net.train import read_checkpoint

    st = read_checkpoint(out / "last.pt")
    assert (st["arch"], st["mode"], st["preset"]) == ("galliani", "e2e", "tiny")
    assert st["net_config"]["reinhard"] is False and st["net_config"]["params"] == {"growth": 4}
    assert st["trained_input"] == {"arch": "galliani", "preset": "tiny", "mode": "e2e",
                                   "input": "ldr", "preprocessing": None, "reinhard_scale": 1.0,
                                   "restores_luminance": False}
    assert st["extra"]["input"] == "ldr"


def test_train_ssr_rejects_bad_arguments(tiny_set, tmp_path, capsys):
    assert main(["train-ssr", str(tmp_path / "missing"), "--out", str(tmp_path / "o")]) == 2
    assert "no such dataset folder" in capsys.readouterr().err
    assert main(["train-ssr", str(tiny_set), "--out", str(tmp_path / "o"), "--epochs", "0"]) == 2
    assert "--epochs" in capsys.readouterr().err
    if not torch.cuda.is_available():
        assert main(["train-ssr", str(tiny_set), "--out", str(tmp_path / "o"),
                     "--device", "cuda", "--quiet"]) == 2
        assert "CUDA is not available" in capsys.readouterr().err
