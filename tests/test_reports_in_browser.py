"""The SSR evaluation report renders in headless Chromium with every image loaded.

CI (``.ci/run``) installs Chromium and sets ``MEHS_REQUIRE_CHROMIUM``: there this test must
run, not skip (issue 17). The dataset report's browser test is in test_dataset_report.py.
"""

import os
import re
import sys
from pathlib import Path

import numpy as np
import pytest

TOOLS = Path(__file__).resolve().parents[1] / "tools"


@pytest.fixture(scope="module")
def chk():
    sys.path.insert(0, str(TOOLS))
    try:
        import check_report_chromium as mod
    finally:
        sys.path.pop(0)
    if mod.find_chromium() is None:
        if os.environ.get("MEHS_REQUIRE_CHROMIUM"):
            pytest.fail("chromium is not installed but MEHS_REQUIRE_CHROMIUM is set")
        pytest.skip("chromium is not installed")
    return mod


def test_evaluation_report_renders_in_headless_chromium(chk, tmp_path):
    from mehs.cube import SpectralCube
    from mehs.dataset.build import build_from_hs
    from mehs.io.envi import write_envi
    from mehs.rgb import WAVELENGTHS_31
    from mehs.ssr.evaluate import evaluate, write_results
    from mehs.ssr.report import write_evaluation_report

    rng = np.random.default_rng(2)
    for i in range(2):
        cube = (rng.random((10, 8, 31), dtype=np.float32) + 0.2).astype(np.float32)
        write_envi(tmp_path / "cubes" / f"c{i}.hdr", SpectralCube(cube, WAVELENGTHS_31))
    ds = tmp_path / "ds"
    build_from_hs([tmp_path / "cubes"], ds, workers=1, progress=False, splits="0,0,1")
    res = evaluate(ds, "smits,mallett", preprocess="off", out=tmp_path / "res", figures=1)
    if not (tmp_path / "res" / "evaluation.json").is_file():
        write_results(res, tmp_path / "res")
    page = write_evaluation_report(tmp_path / "res")
    got = chk.check_report(page)
    assert got["images"] >= 2 and got["broken"] == []
    # and the check can fail: damage the first embedded or linked image
    text = page.read_text(encoding="utf-8")
    bad = re.sub(r"(<img[^>]*src=['\"])([^'\"]+)", r"\1data:image/png;base64,AAAA", text,
                 count=1)
    assert bad != text
    page.write_text(bad, encoding="utf-8")
    assert len(chk.check_report(page)["broken"]) == 1
