"""End-to-end dataset builds on small simulated scenes (issue 6 "Must show")."""

import json
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest

from mehs.dataset import manifest as mf
from mehs.dataset.build import build_dataset, build_from_hs
from mehs.dataset.quality import QualityRules

SIZE = 32
TIMES_MS = (0.05, 0.4, 3.2)
RULES = QualityRules()


def _make_scenes(root: Path) -> list[Path]:
    from mehs.capture.scene import make_scene
    from mehs.capture.sensor import SensorModel
    from mehs.capture.simulate import simulate_bracket, write_simulated_scene

    out = []
    for sid, kind, motion in (("a_still", "colorchecker", False), ("b_window", "window", False),
                              ("c_moving", "colorchecker", True)):
        scene = make_scene(kind, SIZE, SIZE, motion=motion, seed=7)
        sim = simulate_bracket(scene, SensorModel(seed=3), TIMES_MS, seed=0)
        out.append(write_simulated_scene(sim, root / sid, scene_id=sid))
    return out


@pytest.fixture(scope="module")
def scenes(tmp_path_factory):
    return _make_scenes(tmp_path_factory.mktemp("scenes"))


@pytest.fixture(scope="module")
def curve(tmp_path_factory):
    """The simulated sensor is linear: give its curve, as a lab would for a calibrated camera
    (this also keeps these orchestration tests independent of response recovery)."""
    from mehs.synthesis.response import ResponseCurve

    return ResponseCurve.linear(12).save(tmp_path_factory.mktemp("curve") / "linear.json")


@pytest.fixture(scope="module")
def reference(scenes, curve, tmp_path_factory):
    """An uninterrupted single-worker build: the reference every other build must equal."""
    out = tmp_path_factory.mktemp("ref") / "ds"
    commits = []
    m = build_dataset(scenes, out, workers=1, seed=5, rules=RULES, progress=False,
                      response=curve, on_commit=commits.append)
    assert len(commits) == 3
    return out, m


def _snapshot(ds: Path) -> dict[str, bytes]:
    """Every file's bytes, with the manifest stripped of its volatile fields."""
    snap = {}
    for p in sorted(ds.rglob("*")):
        if p.is_file() and p.name != mf.MANIFEST_NAME and "report" not in p.name:
            snap[p.relative_to(ds).as_posix()] = p.read_bytes()
    snap[mf.MANIFEST_NAME] = json.dumps(mf.strip_volatile(mf.read_manifest(ds)),
                                        sort_keys=True).encode()
    return snap


def _assert_same(a: Path, b: Path) -> None:
    sa, sb = _snapshot(a), _snapshot(b)
    assert sorted(sa) == sorted(sb)
    differ = [k for k in sa if sa[k] != sb[k]]
    assert not differ, f"files differ: {differ}"


def test_manifest_flags_the_moving_scene(reference):
    ds, m = reference
    assert m["format"] == "mehs-dataset/1" and len(m["wavelengths"]) == 31
    by = mf.scene_map(m)
    assert sorted(by) == ["a_still", "b_window", "c_moving"]
    assert by["c_moving"]["status"] == "fail"
    assert any("ghost" in r for r in by["c_moving"]["reasons"]), by["c_moving"]["reasons"]
    assert by["c_moving"]["quality"]["ghost_fraction"] > by["a_still"]["quality"]["ghost_fraction"]
    for sid in ("a_still", "b_window"):
        assert by[sid]["status"] == "pass", by[sid]["reasons"]
        q = by[sid]["quality"]
        assert q["dynamic_range_stops"] > 4 and len(q["exposure_ratios"]) >= 2
    split_ids = sorted(sum(m["splits"].values(), []))
    assert split_ids == ["a_still", "b_window"]  # failed scenes never enter a split
    for s in m["scenes"]:
        prov = s["provenance"]
        assert prov["software_version"] and prov["params"]["method"] == "poisson"
        assert "scene.json" in prov["input_sha256"] and len(s["key"]) == 64
        for name, rel in s["files"].items():
            from mehs.io.atomic import sha256_file
            assert sha256_file(ds / rel) == s["sha256"][name]
    rows = (ds / "index.csv").read_text().splitlines()
    assert len(rows) == 4 and rows[3].startswith("c_moving,fail,")
    assert (ds / "splits" / "train.txt").is_file()


def test_files_open_with_spy_and_openexr(reference):
    import OpenEXR
    import spectral

    from mehs.preview import read_png

    ds, m = reference
    files = mf.scene_map(m)["a_still"]["files"]
    img = spectral.envi.open(str(ds / files["hs"]))
    assert img.shape == (SIZE, SIZE, 31) and np.dtype(img.dtype) == np.float32
    np.testing.assert_allclose([float(w) for w in img.metadata["wavelength"]],
                               np.arange(400, 701, 10))
    hs = np.asarray(img.open_memmap())
    assert np.isfinite(hs).all() and hs.max() > 0
    with OpenEXR.File(str(ds / files["hdr_rgb"]), separate_channels=True) as f:
        ch = f.channels()
        assert sorted(ch) == ["B", "G", "R"]
        assert ch["R"].pixels.dtype == np.float16 and ch["R"].pixels.shape == (SIZE, SIZE)
    ldr = read_png(ds / files["ldr_rgb"])
    mask = read_png(ds / files["mask"])
    assert ldr.shape == (SIZE, SIZE, 3) and ldr.dtype == np.uint8
    assert mask.shape == (SIZE, SIZE) and set(np.unique(mask)) <= set(range(16))  # bits 1, 2, 4, 8
    moving = mf.scene_map(m)["c_moving"]["files"]
    assert np.count_nonzero(read_png(ds / moving["mask"]) & 2) > 0


def test_rerun_does_nothing(reference, scenes, curve):
    ds, _ = reference
    before = {p: (p.stat().st_mtime_ns, p.read_bytes()) for p in ds.rglob("*") if p.is_file()}
    commits = []
    build_dataset(scenes, ds, workers=1, seed=5, rules=RULES, progress=False,
                  response=curve, on_commit=commits.append)
    after = {p: (p.stat().st_mtime_ns, p.read_bytes()) for p in ds.rglob("*") if p.is_file()}
    assert commits == [] and after == before


_KILL_SCRIPT = textwrap.dedent("""
    import os, signal, sys
    import mehs.preview
    from mehs.dataset.build import build_dataset
    from mehs.dataset.quality import QualityRules

    committed = []
    real_write_png = mehs.preview.write_png

    def write_png(path, img):  # crash hard (like a power cut) half-way through scene 2
        if committed and path.name == "mask.png":
            os.kill(os.getpid(), signal.SIGKILL)
        return real_write_png(path, img)

    mehs.preview.write_png = write_png
    build_dataset(sys.argv[3:], sys.argv[1], workers=1, seed=5, rules=QualityRules(),
                  response=sys.argv[2], progress=False, on_commit=committed.append)
""")


def test_killed_build_resumes_to_identical_dataset(reference, scenes, curve, tmp_path):
    ds = tmp_path / "ds"
    proc = subprocess.run([sys.executable, "-c", _KILL_SCRIPT, str(ds), str(curve),
                           *map(str, scenes)],
                          capture_output=True, text=True, timeout=300)
    assert proc.returncode == -9, proc.stderr
    m = mf.read_manifest(ds)
    assert [e["id"] for e in m["scenes"]] == ["a_still"]  # the half-built scene is not listed
    half = ds / "scenes" / ".tmp-b_window"
    assert (half / "hs.hdr").is_file() and not (half / "mask.png").exists()
    assert not (ds / "scenes" / "b_window").exists()
    commits = []
    build_dataset(scenes, ds, workers=1, seed=5, rules=RULES, progress=False,
                  response=curve, on_commit=commits.append)
    assert len(commits) == 2
    assert not (ds / ".mehs-build.lock").exists()
    _assert_same(reference[0], ds)


def test_two_workers_match_one_via_cli(reference, scenes, curve, tmp_path):
    from mehs.cli import main

    ds = tmp_path / "ds2"
    rc = main(["build", *map(str, scenes), "--out", str(ds), "--workers", "2", "--seed", "5",
               "--response", str(curve), "--quiet"])
    assert rc == 0
    _assert_same(reference[0], ds)


def test_dask_local_cluster_matches(reference, scenes, curve, tmp_path):
    distributed = pytest.importorskip("distributed")
    ds = tmp_path / "dsd"
    with distributed.LocalCluster(processes=False, n_workers=1, threads_per_worker=2,
                                  dashboard_address=None) as cluster:
        # an address, as `mehs build --scheduler ADDRESS` passes it
        build_dataset(scenes, ds, scheduler=cluster.scheduler_address, seed=5, rules=RULES,
                      progress=False, response=curve)
    _assert_same(reference[0], ds)


def test_force_and_changed_parameters_rebuild(reference, scenes, curve, tmp_path):
    import shutil

    ds = tmp_path / "dsf"
    shutil.copytree(reference[0], ds)
    commits = []
    build_dataset(scenes[:1], ds, workers=1, seed=5, rules=RULES, progress=False, force=True,
                  response=curve, on_commit=commits.append)
    assert [c["id"] for c in commits] == ["a_still"]
    _assert_same(reference[0], ds)
    commits.clear()
    build_dataset(scenes[:1], ds, workers=1, seed=5, rules=RULES, progress=False,
                  response=curve, method="debevec", on_commit=commits.append)
    assert [c["id"] for c in commits] == ["a_still"]
    assert mf.scene_map(mf.read_manifest(ds))["a_still"]["provenance"]["params"]["method"] == "debevec"


def test_broken_scene_is_recorded_not_dropped(scenes, tmp_path):
    import shutil

    broken = tmp_path / "z_broken"
    shutil.copytree(scenes[0], broken)
    doc = json.loads((broken / "scene.json").read_text())
    doc["scene_id"] = "z_broken"
    (broken / "scene.json").write_text(json.dumps(doc))
    for f in broken.rglob("*.raw"):
        f.write_bytes(f.read_bytes()[:100])  # truncated raw data
    ds = tmp_path / "dsb"
    m = build_dataset([broken], ds, workers=1, progress=False)
    (s,) = m["scenes"]
    assert s["status"] == "fail" and s["reasons"][0].startswith("synthesis failed")
    assert s["files"] == {} and not (ds / "scenes" / "z_broken").exists()
    assert m["splits"] == {"train": [], "val": [], "test": []}
    from mehs.cli import main

    assert main(["build", str(broken), "--out", str(tmp_path / "dsb2"), "-q"]) == 1


def test_from_hs_pairs_204_and_31_band_cubes(scenes, tmp_path):
    from mehs.cube import SpectralCube
    from mehs.io.envi import read_envi, write_envi
    from mehs.rgb import WAVELENGTHS_31

    truth = read_envi(scenes[0] / "truth" / "radiance.hdr")
    cubes = tmp_path / "cubes"
    write_envi(cubes / "wide.hdr", truth, dtype=np.float32)
    small = np.random.default_rng(0).random((8, 6, 31), dtype=np.float32)
    small[0, 0] = np.nan  # flagged invalid, stored as 0, never leaked
    write_envi(cubes / "arad.hdr", SpectralCube(small, WAVELENGTHS_31), dtype=np.float32)
    ds = tmp_path / "dsh"
    m = build_from_hs([cubes], ds, workers=1, progress=False)
    by = mf.scene_map(m)
    assert sorted(by) == ["arad", "wide"] and all(s["status"] == "pass" for s in m["scenes"])
    arad = read_envi(ds / by["arad"]["files"]["hs"])
    assert arad.shape == (8, 6, 31)
    np.testing.assert_array_equal(np.asarray(arad.data)[1:], small[1:])
    assert np.asarray(arad.data)[0, 0].tolist() == [0.0] * 31
    from mehs.preview import read_png
    assert read_png(ds / by["arad"]["files"]["mask"])[0, 0] == 4
    assert read_envi(ds / by["wide"]["files"]["hs"]).shape == (SIZE, SIZE, 31)
    assert by["wide"]["quality"]["ghost_fraction"] is None


def test_csv_scene_list_of_specim_folders(reference, scenes, curve, tmp_path):
    exps = sorted((scenes[0] / "exposures").iterdir())
    lst = tmp_path / "scenes.csv"
    lst.write_text("scene_id,folder_short,folder_mid,folder_long\n"
                   "lab_a," + ",".join(str(e) for e in exps) + "\n")
    m = build_dataset([lst], tmp_path / "dsc", workers=1, seed=5, progress=False,
                      response=curve)
    (s,) = m["scenes"]
    assert s["id"] == "lab_a" and s["provenance"]["kind"] == "specim" and "error" not in s
    assert any(k.startswith("2/capture/") for k in s["provenance"]["input_sha256"])
    ref = mf.scene_map(reference[1])["a_still"]
    # the same raw cubes give the same HS cube, whichever way they are listed
    assert s["sha256"]["hs_data"] == ref["sha256"]["hs_data"]
