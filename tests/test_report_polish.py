"""Report and help-text polish (issue 17, item 10): what a reader of the reports sees."""

import re

import numpy as np
import pytest

from mehs.cli import main


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    from mehs.cube import SpectralCube
    from mehs.dataset.build import build_from_hs
    from mehs.io.envi import write_envi
    from mehs.rgb import WAVELENGTHS_31

    root = tmp_path_factory.mktemp("polish")
    rng = np.random.default_rng(1)
    for i in range(2):
        cube = rng.random((8, 6, 31), dtype=np.float32) + 0.1
        write_envi(root / "cubes" / f"c{i}.hdr", SpectralCube(cube, WAVELENGTHS_31))
    ds = root / "dataset"  # the default-looking name that made "mehs dataset dataset"
    build_from_hs([root / "cubes"], ds, workers=1, progress=False)
    return ds


def test_dataset_report_title_does_not_stutter(dataset):
    from mehs.dataset.report import write_report

    page = write_report(dataset).read_text()
    title = re.search(r"<title>(.*?)</title>", page).group(1)
    assert "dataset dataset" not in title and title.endswith(": dataset")


def test_saturation_ghost_scatter_starts_at_zero(dataset, monkeypatch):
    import mehs.dataset.report as rep
    from mehs.dataset.manifest import read_manifest

    seen = {}
    monkeypatch.setattr(rep, "_save", lambda fig, out: seen.update(
        x=fig.axes[1].get_xlim(), y=fig.axes[1].get_ylim()))
    rep._overview_figure(read_manifest(dataset)["scenes"], dataset / "unused.png")
    assert seen["x"][0] == 0 and seen["y"][0] == 0 and seen["x"][1] > 0


def test_exposure_ratios_print_without_scientific_notation():
    from mehs.dataset.report import _fmt_ratios, _row

    assert _fmt_ratios([1.0, 70.6667, 4999.2]) == "1 : 70.7 : 5000"
    row = _row({"id": "a", "status": "pass", "quality": {"exposure_ratios": [1.0, 71.0, 5e3]}},
               "train")
    assert "1 : 71 : 5000" in row and "e+" not in row


def _summary(values: dict[str, dict[str, float]]):
    return [{"input": "hdr", "restore": True, "preprocess": "off", "model": m,
             "n_images": 1, **v} for m, v in values.items()]


def test_a_column_where_every_model_ties_has_no_best():
    from mehs.ssr.evaluate import table_blocks

    s = _summary({"a": {"rmse": 0.0, "psnr": float("inf"), "sam": 2.0},
                  "b": {"rmse": 0.0, "psnr": float("inf"), "sam": 3.0}})
    (_, header, body, bold), = table_blocks(s, metrics=("sam", "rmse", "psnr"))
    assert bold == [[True, False, False], [False, False, False]]
    # a partial tie at the top is still marked on both
    s = _summary({"a": {"sam": 2.0}, "b": {"sam": 2.0}, "c": {"sam": 5.0}})
    (_, _, _, bold), = table_blocks(s, metrics=("sam",))
    assert [r[0] for r in bold] == [True, True, False]


@pytest.mark.parametrize("cmd", ["evaluate", "train-baseline"])
def test_seed_options_have_help(cmd, capsys):
    with pytest.raises(SystemExit):
        main([cmd, "--help"])
    out = capsys.readouterr().out
    line = re.search(r"--seed SEED\s+(\S.*)", out)
    assert line and "seed" in line.group(1).lower()
