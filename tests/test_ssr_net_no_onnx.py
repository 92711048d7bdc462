"""`mehs train-ssr` with the torch extra but without onnx (issue 17, defect 7).

Training must end normally: checkpoints kept, the skipped ONNX export named with the
command that installs what it needs and the call that exports later.
"""

import sys

import pytest

torch = pytest.importorskip("torch")
torch.set_num_threads(1)

from mehs.cli import main  # noqa: E402


def test_train_ssr_without_onnx_keeps_checkpoints_and_says_what_was_skipped(
        tmp_path, capsys, monkeypatch):
    from mehs.ssr.synthetic import make_paired_set

    ds = make_paired_set(tmp_path / "ds", n_scenes=3, size=16, seed=3)
    monkeypatch.setitem(sys.modules, "onnx", None)  # `import onnx` fails as if not installed
    out = tmp_path / "run"
    rc = main(["train-ssr", str(ds), "--out", str(out), "--preset", "tiny", "--patch", "16",
               "--batch", "2", "--patches-per-image", "1", "--epochs", "1", "--quiet"])
    err = capsys.readouterr().err
    assert rc == 0, err
    assert "ONNX export skipped" in err and 'pip install "mehs[onnx]"' in err
    assert "export_onnx(" in err
    assert (out / "best.pt").is_file() or (out / "last.pt").is_file()
    assert not (out / "model.onnx").exists()
    assert not [p for p in out.iterdir() if "onnx" in p.name]  # no partial export left
