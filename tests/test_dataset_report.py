"""`mehs report` on a dataset: static HTML with images beside it, all loading in Chromium."""

import os
import re
import shutil
import sys
from pathlib import Path

import numpy as np
import pytest

from mehs.dataset.build import build_from_hs
from mehs.dataset.report import write_dataset_report, write_report
from mehs.errors import InputError

TOOLS = Path(__file__).resolve().parents[1] / "tools"


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    from mehs.cube import SpectralCube
    from mehs.io.envi import write_envi
    from mehs.rgb import WAVELENGTHS_31

    root = tmp_path_factory.mktemp("rep")
    rng = np.random.default_rng(1)
    for i in range(2):
        cube = rng.random((12, 10, 31), dtype=np.float32) * (10.0 ** rng.uniform(-2, 2, (12, 10, 1)))
        write_envi(root / "cubes" / f"c{i}.hdr", SpectralCube(cube.astype(np.float32), WAVELENGTHS_31))
    # a scene that fails the rules, so the report shows a failure with its reasons
    write_envi(root / "cubes" / "dark.hdr",
               SpectralCube(np.zeros((12, 10, 31), np.float32), WAVELENGTHS_31))
    ds = root / "ds"
    build_from_hs([root / "cubes"], ds, workers=1, progress=False)
    return ds


def test_report_writes_page_and_images(dataset, tmp_path):
    out = write_report(dataset)
    assert out == dataset / "report.html"
    page = out.read_text()
    for sid in ("c0", "c1", "dark"):
        assert f'id="scene-{sid}"' in page
    assert "invalid fraction" in page  # the failing scene's reason is shown
    srcs = re.findall(r'<img src="([^"]+)"', page)
    assert len(srcs) >= 1 + 3 + 2  # overview + thumbnails + figures of the built scenes
    for s in srcs:
        assert not s.startswith(("/", "http")) and (out.parent / s).stat().st_size > 0
    # elsewhere, with --out: images beside the page
    other = write_dataset_report(dataset, tmp_path / "r" / "page.html")
    assert (tmp_path / "r" / "page_files" / "overview.png").is_file() and other.is_file()


def test_report_dispatches_evaluation_folders(dataset, tmp_path, monkeypatch):
    import mehs.ssr.report as ssr_report
    from mehs.cli import main

    calls = []
    monkeypatch.setattr(ssr_report, "write_evaluation_report",
                        lambda d, out=None: calls.append((Path(d), out)) or Path(d) / "r.html")
    results = tmp_path / "results"
    results.mkdir()
    with pytest.raises(InputError, match="neither a dataset"):
        write_report(results)
    (results / "evaluation.json").write_text("{}")
    assert main(["report", str(results)]) == 0
    assert calls == [(results, None)]
    assert main(["report", str(dataset), "--out", str(tmp_path / "d.html")]) == 0
    assert len(calls) == 1 and (tmp_path / "d.html").is_file()


def test_report_renders_in_headless_chromium(dataset):
    sys.path.insert(0, str(TOOLS))
    try:
        import check_report_chromium as chk
    finally:
        sys.path.pop(0)
    if chk.find_chromium() is None:
        if os.environ.get("MEHS_REQUIRE_CHROMIUM"):  # set by .ci/run: CI must not skip this
            pytest.fail("chromium is not installed but MEHS_REQUIRE_CHROMIUM is set")
        pytest.skip("chromium is not installed")
    out = write_report(dataset)
    res = chk.check_report(out)
    assert res["images"] >= 6 and res["broken"] == []
    # and the check can fail: break one image
    victim = out.parent / "report_files" / "overview.png"
    saved = victim.read_bytes()
    try:
        victim.write_bytes(b"not a png")
        assert chk.check_report(out)["broken"] == ["report_files/overview.png"]
    finally:
        victim.write_bytes(saved)


def test_response_figure_reads_per_band_curves_by_their_level_count(tmp_path):
    import json

    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    from mehs.dataset.report import _plot_response

    # an 8-bit camera with 300 bands: more curves than levels
    g = np.log(np.maximum(np.arange(256.0), 0.5))[None].repeat(300, axis=0)
    p = tmp_path / "response.json"
    p.write_text(json.dumps({"levels": 256, "g": g.tolist()}))
    fig, ax = plt.subplots()
    _plot_response(ax, p)
    assert ax.lines and all(len(line.get_xdata()) == 256 for line in ax.lines)
    plt.close(fig)
