"""Audit of the dataset report's figures: numbers as in the manifest, unknown figures shown as
unknown (not 0), the dynamic-range histogram over the pixels the figure counts, units, orientation."""

import json

import numpy as np
import pytest

import mehs.dataset.report as rep
from mehs.dataset.manifest import read_manifest


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    """Two HS cubes (no bracket: saturation/ghost figures unknown), 12 lines × 20 samples,
    asymmetric: a bright block in the top-left corner, a dark right half."""
    from mehs.cube import SpectralCube
    from mehs.dataset.build import build_from_hs
    from mehs.io.envi import write_envi
    from mehs.rgb import WAVELENGTHS_31

    root = tmp_path_factory.mktemp("qrep")
    rng = np.random.default_rng(4)
    for i in range(2):
        cube = (rng.random((12, 20, 31)) * 0.5 + 0.5).astype(np.float32)
        cube[:4, :6] *= 200.0     # bright block, top-left
        cube[:, 10:] *= 0.05      # dark right half
        write_envi(root / "cubes" / f"h{i}.hdr", SpectralCube(cube, WAVELENGTHS_31))
    ds = root / "ds"
    build_from_hs([root / "cubes"], ds, workers=1, progress=False)
    return ds


def _capture(monkeypatch):
    seen = {}
    monkeypatch.setattr(rep, "_save", lambda fig, out: seen.setdefault("fig", fig))
    return seen


def test_overview_draws_unknown_figures_as_missing_not_zero(dataset, monkeypatch):
    scenes = read_manifest(dataset)["scenes"]
    assert all(s["quality"]["saturated_fraction"] is None for s in scenes)
    scenes = scenes + [{"id": "broken", "status": "fail", "quality": {}}]  # not built: no DR
    seen = _capture(monkeypatch)
    rep._overview_figure(scenes, dataset / "unused.png")
    bars, scatter = seen["fig"].axes
    heights = [p.get_height() for p in bars.patches]
    assert len(heights) == 2 and all(h > 4 for h in heights)  # no 0-stop bar for "broken"
    assert any(t.get_text() == "n/a" for t in bars.texts)
    # no point at (0, 0) for scenes whose saturation and ghosts were never measured
    assert sum(len(c.get_offsets()) for c in scatter.collections) == 0
    assert "(3 not measured)" in scatter.get_title()


def test_scene_maps_show_the_manifests_figures_and_unknown_as_not_measured(dataset, monkeypatch):
    m = read_manifest(dataset)
    s = m["scenes"][0]
    seen = _capture(monkeypatch)
    rep._scene_figure(dataset, s, dataset / "unused.png", m.get("radiance_unit"))
    titles = [ax.get_title() for ax in seen["fig"].axes]
    assert "saturated in every exposure: not measured" in titles
    assert "ghost (moved between exposures): not measured" in titles
    # a measured figure is the manifest's number, formatted as in the table
    seen.clear()
    s2 = {**s, "quality": {**s["quality"], "saturated_fraction": 0.0123, "ghost_fraction": 0.0}}
    rep._scene_figure(dataset, s2, dataset / "unused.png")
    titles = [ax.get_title() for ax in seen["fig"].axes]
    assert "saturated in every exposure: 1.23 %" in titles
    assert "ghost (moved between exposures): 0.00 %" in titles


def test_dynamic_range_histogram_counts_the_saturated_lamp_as_the_figure_does(dataset,
                                                                              monkeypatch):
    """DR counts pixels saturated in every exposure (bit 1) with their lower bound; the
    histogram drawn under the DR title must show them too."""
    from mehs.io.exr import read_exr
    from mehs.preview import write_png
    from mehs.rgb import luminance

    m = read_manifest(dataset)
    s = m["scenes"][0]
    Y = luminance(read_exr(dataset / s["files"]["hdr_rgb"]).data[:, :, :3])
    mask = np.zeros(Y.shape, np.uint8)
    mask[:4, :6] = 1            # the bright block "saturated in every exposure"
    mask[11, 19] = 2            # a ghost and an invalid pixel stay out
    mask[11, 18] = 4
    write_png(dataset / "lamp_mask.png", mask)
    s = {**s, "files": {**s["files"], "mask": "lamp_mask.png"}}
    seen = _capture(monkeypatch)
    rep._scene_figure(dataset, s, dataset / "unused.png")
    hist = seen["fig"].axes[2]
    edges = [p.get_x() for p in hist.patches] + [p.get_x() + p.get_width() for p in hist.patches]
    counts = sum(p.get_height() for p in hist.patches)
    assert max(edges) >= np.log2(Y[:4, :6].max()) - 1e-6
    assert counts == Y.size - 2


def test_example_spectra_leave_gaps_for_zero_samples_and_label_the_unit(dataset, monkeypatch):
    from mehs.io.envi import read_envi, write_envi

    m = read_manifest(dataset)
    s = m["scenes"][1]
    cube = read_envi(dataset / s["files"]["hs"])
    data = np.array(cube.data)
    data[:, :, 5] = 0.0         # a band that measured nothing
    write_envi(dataset / "zeros.hdr", cube.with_data(data), dtype=np.float32)
    s = {**s, "files": {**s["files"], "hs": "zeros.hdr"},
         "quality": {**s["quality"], "radiance_scale": 0.25}}
    seen = _capture(monkeypatch)
    rep._scene_figure(dataset, s, dataset / "unused.png", "W sr-1 m-2 nm-1")
    ax = seen["fig"].axes[5]
    assert ax.get_ylim()[0] > 1e-3   # not stretched down to a 1e-12 clamp
    for line in ax.get_lines():
        assert np.isnan(line.get_ydata()[5])
    assert ax.get_ylabel() == "radiance [W sr-1 m-2 nm-1] × 0.25"


def test_pictures_keep_the_cube_orientation(dataset):
    """The thumbnail and the per-scene preview are (lines, samples) like the cube: the bright
    block stays top-left, the dark half right (no transpose or flip)."""
    from mehs.preview import read_png

    page = rep.write_report(dataset)
    m = read_manifest(dataset)
    for s in m["scenes"]:
        for img in (read_png(dataset / s["files"]["preview"]),
                    read_png(page.parent / "report_files" / f"{s['id']}_thumb.png")):
            assert img.shape[:2] == (12, 20)
            g = img.astype(float).mean(axis=2)
            assert g[:4, :6].mean() > g[4:, :10].mean() > g[:, 10:].mean()


def test_unrecorded_calibration_uncertainty_is_not_shown_as_zero():
    html_ = rep._radiometry({"radiance_unit": "W sr-1 m-2 nm-1",
                             "calibration": {"method": "sphere", "path": "cal.json"}})
    assert "not recorded" in html_ and "0.00%" not in html_
    html_ = rep._radiometry({"radiance_unit": "W sr-1 m-2 nm-1",
                             "calibration": {"median_uncertainty": 0.0123}})
    assert "1.23%" in html_


def test_table_numbers_are_the_manifests(dataset):
    page = rep.write_report(dataset).read_text()
    for s in read_manifest(dataset)["scenes"]:
        dr = s["quality"]["dynamic_range_stops"]
        inv = s["quality"]["invalid_fraction"]
        row = next(r for r in page.split("<tr") if f"#scene-{s['id']}'" in r)
        assert f"<td>{dr:.3g}</td>" in row and f"<td>{inv * 100:.2f} %</td>" in row
        assert row.count("<td>–</td>") >= 2   # unknown saturated / ghost
    assert rep._fmt(0, pct=True) == "0.00 %" and rep._fmt(1000) == "1000"
    json.dumps(read_manifest(dataset))
