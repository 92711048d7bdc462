"""A new lab user's common mistakes on the command line: one ``mehs: error:`` line naming the
path and the problem, exit status 2, and nothing written.

Found by running every documented command on a core install (no extras): a one-exposure
"bracket" was captured (and then refused by fuse, build and calibrate), ``--times -1,5`` was
an argparse puzzle, ``--out`` into an unrelated non-empty folder mixed outputs into it,
``train-baseline`` wrote into a raw capture, an unwritable ``--out`` was found only after the
stage had moved, and an interrupted build said only "interrupted".
"""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np
import pytest

from mehs.cli import main
from mehs.ssr.synthetic import make_paired_set


def _fails(capsys, argv, *needles) -> str:
    code = main([str(a) for a in argv])
    err = capsys.readouterr().err
    assert code == 2, err
    assert err.startswith("mehs: error:") and "Traceback" not in err, err
    assert len(err.strip().splitlines()) == 1, err
    for n in needles:
        assert str(n) in err, err
    return err


def _tree(folder: Path) -> dict[str, int]:
    return {str(p.relative_to(folder)): p.stat().st_mtime_ns for p in folder.rglob("*")}


def _foreign(tmp_path: Path) -> Path:
    own = tmp_path / "thesis"
    own.mkdir()
    (own / "chapter1.tex").write_text("my own file")
    return own


@pytest.fixture(scope="module")
def pairs(tmp_path_factory):
    # one scene: a train split only (no test, no val)
    return make_paired_set(tmp_path_factory.mktemp("pairs") / "ds", n_scenes=1, size=8, seed=3)


@pytest.fixture(scope="module")
def cube31(tmp_path_factory):
    from mehs.cube import SpectralCube
    from mehs.io import write_envi
    from mehs.rgb import WAVELENGTHS_31

    path = tmp_path_factory.mktemp("cube") / "hs.hdr"
    data = np.random.default_rng(0).uniform(0.1, 1.0, (6, 5, 31)).astype(np.float32)
    write_envi(path, SpectralCube(data, WAVELENGTHS_31.astype(np.float64)))
    return path


# ------------------------------------------------------------------ capture --times


def test_capture_refuses_a_one_exposure_bracket_before_anything(tmp_path, capsys):
    out = tmp_path / "scene"
    _fails(capsys, ["capture", "--simulate", "--size", "8", "--times", "5", "--out", out],
           "--times needs two or more", "'5'")
    assert not out.exists()


@pytest.mark.parametrize("times", ["-1,5", "-5"])
def test_capture_negative_times_are_named_not_an_argparse_puzzle(tmp_path, capsys, times):
    out = tmp_path / "scene"
    _fails(capsys, ["capture", "--simulate", "--size", "8", "--times", times, "--out", out],
           "integration times must be positive" if "," in times else "--times needs two")
    assert not out.exists()


def test_capture_into_an_unwritable_folder_is_refused_before_the_devices_start(
        tmp_path, capsys, monkeypatch):
    # root may write anywhere: the access check is what is tested
    from mehs.cli import _overwrite

    ro = tmp_path / "ro"
    ro.mkdir()
    real = os.access
    monkeypatch.setattr(_overwrite.os, "access",
                        lambda p, m: False if Path(p) == ro else real(p, m))
    started = []
    import mehs.cli.sim_device as sim

    monkeypatch.setattr(sim, "build_devices", lambda *a, **k: started.append(1))
    _fails(capsys, ["capture", "--simulate", "--size", "8", "--times", "1,4",
                    "--out", ro / "scene"], "cannot write here", "permission denied")
    assert not started and not (ro / "scene").exists()


# ------------------------------------------------------------------ --out an unrelated folder


def test_rgb_refuses_an_unrelated_non_empty_out_folder(tmp_path, capsys, cube31):
    own = _foreign(tmp_path)
    before = _tree(own)
    _fails(capsys, ["rgb", cube31, "--out", own], own, "holds other files", "chapter1.tex")
    assert _tree(own) == before
    # --force writes beside them; an empty folder or the command's own earlier outputs are fine
    assert main(["rgb", str(cube31), "--out", str(own), "--force"]) == 0
    assert (own / "rgb.json").is_file() and (own / "chapter1.tex").is_file()
    empty = tmp_path / "empty"
    empty.mkdir()
    (empty / ".DS_Store").write_text("")
    assert main(["rgb", str(cube31), "--out", str(empty)]) == 0


def test_evaluate_refuses_an_unrelated_non_empty_out_folder(tmp_path, capsys, pairs):
    own = _foreign(tmp_path)
    before = _tree(own)
    _fails(capsys, ["evaluate", pairs, "--models", "smits", "--out", own], own,
           "holds other files")
    assert _tree(own) == before


def test_build_refuses_an_unrelated_non_empty_out_folder(tmp_path, capsys, cube31):
    own = _foreign(tmp_path)
    before = _tree(own)
    _fails(capsys, ["build", "--from-hs", cube31, "--out", own], own,
           "holds other files", "not a mehs dataset")
    assert _tree(own) == before


def test_paper_refuses_an_unrelated_non_empty_out_folder(tmp_path, capsys, pairs):
    own = _foreign(tmp_path)
    before = _tree(own)
    _fails(capsys, ["paper", pairs, "--out", own, "--quick"], own, "holds other files")
    assert _tree(own) == before


# ------------------------------------------------------------------ raw captures


def test_train_baseline_never_writes_into_a_raw_capture(tmp_path, capsys, pairs):
    cap = tmp_path / "scene"
    cap.mkdir()
    (cap / "scene.json").write_text("{}")
    _fails(capsys, ["train-baseline", pairs, "--out", cap / "reg.npz", "--split", "all"],
           "raw capture")
    assert sorted(p.name for p in cap.iterdir()) == ["scene.json"]


# ------------------------------------------------------------------ interrupted build


def test_interrupted_build_says_what_it_holds_and_how_to_finish(tmp_path, capsys, monkeypatch):
    """Ctrl-C after the first committed scene: exit 130, the manifest lists only that scene
    (no half scene listed or left looking complete), and the user is told the dataset is
    not finished and how to finish it."""
    import mehs.dataset.build as build_mod

    scenes = []
    for i in range(2):
        s = tmp_path / f"s{i}"
        assert main(["capture", "--simulate", "--size", "8", "--seed", str(i), "--times",
                     "1,4", "--dark-lines", "2", "--white-lines", "2", "--no-progress",
                     "--out", str(s)]) == 0
        scenes.append(s)
    real = build_mod.build_dataset

    def interrupted(*a, **k):
        def stop(entry):
            raise KeyboardInterrupt
        return real(*a, **{**k, "on_commit": stop})

    monkeypatch.setattr(build_mod, "build_dataset", interrupted)
    capsys.readouterr()
    ds = tmp_path / "ds"
    code = main(["build", *map(str, scenes), "--out", str(ds), "--workers", "1", "--quiet"])
    err = capsys.readouterr().err
    assert code == 130, err
    assert "Traceback" not in err
    assert "interrupted" in err and "1 committed scene(s)" in err
    assert "run the same command again" in err
    manifest = json.loads((ds / "manifest.json").read_text())
    listed = {s["id"] for s in manifest["scenes"]}
    assert len(listed) == 1
    visible = {p.name for p in (ds / "scenes").iterdir() if not p.name.startswith(".")}
    assert visible == listed
    # and the same command finishes it
    monkeypatch.setattr(build_mod, "build_dataset", real)
    assert main(["build", *map(str, scenes), "--out", str(ds), "--workers", "1", "--quiet"]) == 0
    manifest = json.loads((ds / "manifest.json").read_text())
    assert {s["id"] for s in manifest["scenes"]} == {"s0", "s1"}
