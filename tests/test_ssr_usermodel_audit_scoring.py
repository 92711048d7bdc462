"""Audit of user Python / TorchScript models in `mehs evaluate`: declarations and numbers.

The oracle is a fixed linear map declared as trained on HDR, no pre-processing, end to
end; its scores are recomputed here from the dataset files read with outside readers
(SPy for the ENVI cube, OpenEXR for the HDR-RGB, Pillow for the mask) and numpy.
"""

import csv
import textwrap

import numpy as np
import pytest

from mehs.cli import main
from mehs.ssr.contract import trained_for
from mehs.ssr.models import load_model
from mehs.ssr.synthetic import make_paired_set

A = (np.random.default_rng(5).random((31, 3)) * 0.5).astype(np.float32)

USER_FILE = textwrap.dedent("""
    import numpy as np
    from mehs.ssr.contract import TrainedFor

    A = np.array({A})

    def linear(rgb):
        return np.einsum("bc,hwc->hwb", A, rgb).astype(np.float32)

    linear.trained_for = TrainedFor(input="hdr", preprocessing=None, output="spectra")
""")


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    return make_paired_set(tmp_path_factory.mktemp("um") / "ds", n_scenes=3, size=32, seed=3)


@pytest.fixture
def user_file(tmp_path):
    p = tmp_path / "usermodel.py"
    p.write_text(USER_FILE.format(A=A.tolist()))
    return p


def independent_scores(dataset):
    """SAM (°), MRAE, RMSE, PSNR per image of the oracle, from the files, then averaged."""
    OpenEXR = pytest.importorskip("OpenEXR")
    spectral = pytest.importorskip("spectral")
    from PIL import Image

    out = []
    for row in csv.DictReader((dataset / "index.csv").open()):
        gt = np.asarray(spectral.open_image(str(dataset / row["hs"])).load(), dtype=np.float64)
        rgb = np.asarray(OpenEXR.File(str(dataset / row["hdr_rgb"])).channels()["RGB"].pixels,
                         dtype=np.float32)
        keep = np.asarray(Image.open(dataset / row["mask"])) == 0
        pred = np.einsum("bc,hwc->hwb", A, rgb).astype(np.float32).astype(np.float64)
        P, G = pred[keep], gt[keep]
        cos = (P * G).sum(1) / (np.linalg.norm(P, axis=1) * np.linalg.norm(G, axis=1))
        sam = np.degrees(np.arccos(np.clip(cos, -1, 1))).mean()
        pos = G > 0
        mrae = (np.abs(P - G)[pos] / G[pos]).mean()
        mse = ((P - G) ** 2).mean()
        out.append((sam, mrae, np.sqrt(mse), 10 * np.log10(G.max() ** 2 / mse)))
    return np.mean(out, axis=0)


def test_declared_user_function_is_scored_only_where_declared_with_exact_numbers(
        dataset, user_file, tmp_path, capsys):
    # the declaration was dropped by the function wrapper: the model was scored in all
    # four settings as undeclared, restored and fed Reinhard-mapped input (MRAE 102)
    m = load_model(f"{user_file}:linear")
    assert trained_for(m).declared and trained_for(m).output == "spectra"
    out = tmp_path / "ev"
    assert main(["evaluate", str(dataset), "--models", f"lin={user_file}:linear", "--out",
                 str(out), "--split", "all", "--figures", "0"]) == 0
    printed = capsys.readouterr().out
    assert "declares no trained input" not in printed
    rows = list(csv.DictReader((out / "summary.csv").open()))
    assert [(r["input"], r["preprocess"], r["restore"]) for r in rows] == [("hdr", "off", "False")]
    got = [float(rows[0][k]) for k in ("sam", "mrae", "rmse", "psnr")]
    want = independent_scores(dataset)
    np.testing.assert_allclose(got, want, rtol=1e-5)
    assert f"{want[0]:.3f}" in printed and f"{want[1]:.4f}" in printed


torch = pytest.importorskip("torch")
pytestmark = pytest.mark.filterwarnings("ignore:`torch.jit:DeprecationWarning")


class _Net(torch.nn.Module):
    def __init__(self, bands=31):
        super().__init__()
        self.conv = torch.nn.Conv2d(3, bands, 1)
        self.drop = torch.nn.Dropout(0.5)
        self.bn = torch.nn.BatchNorm2d(bands)

    def forward(self, x):
        return self.bn(self.drop(self.conv(x)))


def test_torchscript_file_runs_in_eval_mode_without_grad(tmp_path):
    torch.manual_seed(0)
    net = _Net()
    torch.jit.script(net.train()).save(str(tmp_path / "net.pt"))  # saved while training
    m = load_model(str(tmp_path / "net.pt"))
    rgb = np.random.default_rng(0).random((12, 10, 3)).astype(np.float32)
    a, b = m(rgb), m(rgb)
    np.testing.assert_array_equal(a, b)            # dropout off, BN running stats
    with torch.no_grad():
        want = net.eval()(torch.from_numpy(rgb.transpose(2, 0, 1).copy())[None])
    np.testing.assert_allclose(a, want[0].permute(1, 2, 0).numpy(), rtol=1e-5, atol=1e-6)
    assert a.shape == (12, 10, 31) and m.wavelengths.size == 31


def test_torchscript_band_count_and_bare_state_dict_are_explained(tmp_path):
    from mehs.errors import FormatError, InputError

    torch.jit.script(_Net(16).eval()).save(str(tmp_path / "b16.pt"))
    rgb = np.zeros((4, 5, 3), np.float32)
    with pytest.raises(InputError, match="16 bands"):
        load_model(str(tmp_path / "b16.pt"))(rgb)
    assert load_model(str(tmp_path / "b16.pt"),
                      wavelengths=np.arange(400, 560, 10.0))(rgb).shape == (4, 5, 16)
    (tmp_path / "b16.pt.json").write_text(
        '{"wavelengths": [%s], "trained_for": {"input": "hdr", "output": "shape"}}'
        % ", ".join(str(w) for w in range(400, 560, 10)))
    m = load_model(str(tmp_path / "b16.pt"))
    assert m(rgb).shape == (4, 5, 16) and trained_for(m).output == "shape"
    torch.save({"state_dict": _Net().state_dict()}, str(tmp_path / "weights.pth"))
    with pytest.raises(FormatError, match="bare weights"):
        load_model(str(tmp_path / "weights.pth"))
