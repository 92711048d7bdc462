"""Same captures, same dataset bytes, wherever the build machine keeps them.

A lab shares datasets and compares builds by their bytes (docs/formats.md, "Volatile
fields": only ``scenes[].provenance.run`` may differ between two builds of the same inputs
and parameters). Two copies of the same captures, response curve and calibration in two
folders are the same inputs; the truth compared against is the other build's bytes.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest

from mehs.dataset import manifest as mf

SIZE = 16
TIMES_MS = (0.05, 0.4, 3.2)


@pytest.fixture(scope="module")
def lab(tmp_path_factory):
    """Two captures, the linear response curve and a calibration in ``lab/`` and a copy in
    ``elsewhere/deeper/lab/``."""
    from mehs.calibration import calibrate_source_absolute, load_spectrum
    from mehs.calibration.targets import sphere_certificate
    from mehs.capture.scene import make_scene
    from mehs.capture.sensor import SensorModel
    from mehs.capture.simulate import simulate_bracket, write_simulated_scene
    from mehs.synthesis.bracket import load_bracket
    from mehs.synthesis.response import ResponseCurve

    root = tmp_path_factory.mktemp("det")
    a = root / "lab"
    sensor = SensorModel(seed=3)
    for sid, kind, motion in (("still", "colorchecker", False), ("moving", "colorchecker", True)):
        sim = simulate_bracket(make_scene(kind, SIZE, SIZE, motion=motion, seed=7), sensor,
                               TIMES_MS, seed=0)
        write_simulated_scene(sim, a / "scenes" / sid, scene_id=sid)
    sphere = simulate_bracket(make_scene("sphere", 4, SIZE), sensor, (5.0, 20.0, 40.0))
    cal = calibrate_source_absolute(load_bracket(write_simulated_scene(sphere, root / "sphere")),
                                    load_spectrum(sphere_certificate(root / "cert.csv")))
    cal.save(a / "cal.json")
    ResponseCurve.linear(12).save(a / "linear.json")
    b = root / "elsewhere" / "deeper" / "lab"
    shutil.copytree(a, b)
    return a, b


def _build(lab: Path, out: Path, **kw) -> dict:
    from mehs.dataset.build import build_dataset

    scenes = [lab / "scenes" / s for s in ("still", "moving")]
    return build_dataset(scenes, out, workers=1, progress=False, response=lab / "linear.json",
                         **kw)


def _files(ds: Path) -> dict[str, bytes]:
    return {p.relative_to(ds).as_posix(): p.read_bytes() for p in sorted(ds.rglob("*"))
            if p.is_file() and p.name != mf.MANIFEST_NAME}


def _differing(a: Path, b: Path) -> list[str]:
    fa, fb = _files(a), _files(b)
    assert sorted(fa) == sorted(fb)
    out = [k for k in fa if fa[k] != fb[k]]
    ma, mb = (mf.strip_volatile(mf.read_manifest(d)) for d in (a, b))
    for sa, sb in zip(ma["scenes"], mb["scenes"]):
        out += [f"manifest {sa['id']}.{k}" for k in sorted(sa) if sa[k] != sb.get(k)]
    return out


def test_dataset_bytes_do_not_depend_on_where_the_captures_lie(lab, tmp_path):
    a, b = lab
    _build(a, tmp_path / "ds_a")
    _build(b, tmp_path / "ds_b")
    assert _differing(tmp_path / "ds_a", tmp_path / "ds_b") == []
    ma, mb = (json.loads((tmp_path / d / mf.MANIFEST_NAME).read_text()) for d in ("ds_a", "ds_b"))
    assert mf.strip_volatile(ma) == mf.strip_volatile(mb)
    # where each build read its inputs is still recorded, in the volatile part
    for m, root in ((ma, a), (mb, b)):
        for s in m["scenes"]:
            run = s["provenance"]["run"]
            assert run["inputs"] == [str(root / "scenes" / s["id"])]
            assert run["response"] == str(root / "linear.json")
            assert s["provenance"]["inputs"] == [s["id"]]
            assert s["provenance"]["params"]["response"] == "linear.json"
    for ds in ("ds_a", "ds_b"):
        fusion = (tmp_path / ds / "scenes" / "still" / "fusion.json").read_text()
        assert str(tmp_path) not in fusion and str(a.parent) not in fusion


def test_calibrated_scene_files_do_not_depend_on_where_the_calibration_lies(lab, tmp_path):
    a, b = lab
    ma = _build(a, tmp_path / "ds_a", calibration=a / "cal.json")
    mb = _build(b, tmp_path / "ds_b", calibration=b / "cal.json")
    assert [s["status"] for s in ma["scenes"]] == [s["status"] for s in mb["scenes"]]
    assert all(s["files"] for s in ma["scenes"]), [s.get("error") for s in ma["scenes"]]
    # every data file (fusion.json holds the calibration record) and every scene entry;
    # the manifest's top-level calibration record (mehs.dataset.build) is not checked here
    assert _differing(tmp_path / "ds_a", tmp_path / "ds_b") == []
    fusion = json.loads((tmp_path / "ds_a" / "scenes" / "still" / "fusion.json").read_text())
    assert fusion["calibration"]["sha256"] == ma["calibration"]["sha256"]
    assert "path" not in fusion["calibration"] and "source" not in fusion
    assert ma["scenes"][0]["provenance"]["run"]["calibration"] == str(a / "cal.json")


def test_copied_dataset_still_verifies_and_loads(lab, tmp_path):
    """The dataset moved away from its inputs (which are then gone) verifies and scores."""
    from mehs.dataset.quality import QualityRules
    from mehs.ssr.data import load_pairs

    a, _ = lab
    rules = QualityRules(max_ghost_fraction=1.0)
    _build(a, tmp_path / "ds", rules=rules, splits=(1.0, 0.0, 0.0))
    moved = tmp_path / "moved" / "ds"
    shutil.copytree(tmp_path / "ds", moved)
    shutil.rmtree(tmp_path / "ds")
    pairs = list(load_pairs(moved, split="train", verify="full"))
    assert sorted(p.id for p in pairs) == ["moving", "still"]
    for p in pairs:
        assert p.hs_array()[0].shape == (SIZE, SIZE, 31) and p.hdr_rgb().shape == (SIZE, SIZE, 3)
