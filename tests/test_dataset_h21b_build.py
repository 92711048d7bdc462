"""Build warnings: printed for committed scenes when a build is interrupted, naming the
scene's final folder; half-float underflow counts in the scene's quality block.

A cube spanning ~53 stops (one pixel at 1e4, the rest at 1e-12) cannot keep its dim part in
half floats whatever the scale: writing hdr_rgb.exr flushes it to 0 and warns
(HalfFloatUnderflowWarning, naming the file it wrote: ``scenes/.tmp-<id>/hdr_rgb.exr``).
"""

import re
from pathlib import Path

import numpy as np
import pytest

from mehs.dataset import manifest as mf
from mehs.dataset.build import build_from_hs

UNDERFLOW = "lie below the half-float range"


def _write_cubes(root: Path, ids, dim: bool = True) -> Path:
    from mehs.cube import SpectralCube
    from mehs.io.envi import write_envi
    from mehs.rgb import WAVELENGTHS_31

    for sid in ids:
        if dim:
            c = np.full((6, 8, 31), 1e-12, np.float32)
            c[0, 0] = np.float32(1e4)
        else:
            c = np.random.default_rng(1).random((6, 8, 31), dtype=np.float32) + np.float32(0.1)
        write_envi(root / "cubes" / f"{sid}.hdr", SpectralCube(c, WAVELENGTHS_31))
    return root / "cubes"


@pytest.fixture(scope="module")
def dim_cubes(tmp_path_factory) -> Path:
    return _write_cubes(tmp_path_factory.mktemp("dim"), ("a", "b", "c"))


def _warning_lines(err: str) -> list[str]:
    return [ln for ln in err.splitlines() if ln.startswith("mehs build: scene ")]


def _scenes(lines: list[str]) -> list[str]:
    return [re.match(r"mehs build: scene (\w+): ", ln).group(1) for ln in lines]


@pytest.mark.parametrize("exc", [KeyboardInterrupt, RuntimeError])
def test_interrupted_build_prints_the_committed_scenes_warnings(dim_cubes, tmp_path, capsys,
                                                                exc):
    committed = []

    def stop_after_b(entry):
        committed.append(entry["id"])
        if entry["id"] == "b":
            raise exc("stopped")

    with pytest.raises(exc):
        build_from_hs([dim_cubes], tmp_path / "ds", workers=1, progress=False,
                      on_commit=stop_after_b)
    assert committed == ["a", "b"]
    lines = _warning_lines(capsys.readouterr().err)
    assert _scenes(lines) == ["a", "b"]
    assert all(UNDERFLOW in ln for ln in lines)
    # what was printed is what the manifest keeps for those scenes
    m = mf.read_manifest(tmp_path / "ds")
    assert sorted(e["id"] for e in m["scenes"]) == ["a", "b"]


def test_normal_build_prints_each_warning_once(dim_cubes, tmp_path, capsys):
    build_from_hs([dim_cubes], tmp_path / "ds", workers=1, progress=False)
    lines = _warning_lines(capsys.readouterr().err)
    assert _scenes(lines) == ["a", "b", "c"]


def test_warnings_name_the_committed_scene_folder(dim_cubes, tmp_path, capsys):
    ds = tmp_path / "ds"
    m = build_from_hs([dim_cubes], ds, workers=1, progress=False)
    err = capsys.readouterr().err
    assert ".tmp-" not in err, err
    for e in m["scenes"]:
        (w,) = e["provenance"]["run"]["warnings"]
        assert w["category"] == "mehs.io.exr.HalfFloatUnderflowWarning"
        assert ".tmp-" not in w["message"]
        named = Path(w["message"].split(": ", 1)[0])
        assert named == ds / "scenes" / e["id"] / "hdr_rgb.exr" and named.is_file()
        assert f"mehs build: scene {e['id']}: {named}: " in err


def test_relocate_rewrites_only_the_exact_temporary_folder_component():
    from mehs.dataset.scene_warnings import relocate_paths

    log = [{"category": "UserWarning", "count": 1, "message":
            "/d/scenes/.tmp-s1/hdr_rgb.exr: bad; see /d/scenes/.tmp-s10/x and "
            "scenes/.tmp-s1 and .tmp-s1 alone, /d/other/.tmp-s1/y, C:\\d\\scenes\\.tmp-s1\\z"}]
    relocate_paths(log, ".tmp-s1", "s1")
    assert log[0]["message"] == (
        "/d/scenes/s1/hdr_rgb.exr: bad; see /d/scenes/.tmp-s10/x and "
        "scenes/s1 and .tmp-s1 alone, /d/other/.tmp-s1/y, C:\\d\\scenes\\s1\\z")


def test_half_float_underflow_counts_are_in_the_quality_block(dim_cubes, tmp_path):
    import OpenEXR

    ds = tmp_path / "ds"
    m = build_from_hs([dim_cubes / "a.hdr"], ds, workers=1, progress=False)
    (e,) = m["scenes"]
    q = e["quality"]
    hdr = OpenEXR.File(str(ds / e["files"]["hdr_rgb"]), header_only=True).header()
    assert q["half_flushed_to_zero"] == hdr["mehsHalfFlushedToZero"] > 0
    assert type(q["half_flushed_to_zero"]) is int and type(q["half_subnormal"]) is int
    assert q["half_subnormal"] == hdr.get("mehsHalfSubnormal", 0)
    assert e["status"] == "pass"                 # recorded, not a reason to fail the scene
    assert not any(re.search("half", r) for r in e["reasons"])


def test_a_scene_in_range_records_zero_underflow(tmp_path):
    cubes = _write_cubes(tmp_path, ("n",), dim=False)
    m = build_from_hs([cubes], tmp_path / "ds", workers=1, progress=False)
    q = m["scenes"][0]["quality"]
    assert (q["half_flushed_to_zero"], q["half_subnormal"]) == (0, 0)
    assert "warnings" not in m["scenes"][0]["provenance"]["run"]
