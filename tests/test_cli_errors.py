"""Bad input through every ``mehs`` sub-command, as a lab user would hit it.

Each case asserts what design.md "What done means" asks of bad input: a
non-zero exit (2 for a :class:`~mehs.errors.MehsError`), stderr starting with
``mehs: error:`` and naming the file or option at fault, no traceback, no file
created or changed beside the inputs, and no partial output left behind.
"""

from __future__ import annotations

import json
import os
import shutil
import socket
import subprocess
import sys
import threading
from pathlib import Path

import numpy as np
import pytest

from mehs.cli import main

# ------------------------------------------------------------------ fixtures


def _cube(path: Path, data: np.ndarray, wavelengths) -> Path:
    from mehs.cube import SpectralCube
    from mehs.io.envi import write_envi

    return write_envi(path, SpectralCube(data, wavelengths), dtype=np.float32)


@pytest.fixture(scope="module")
def fx(tmp_path_factory) -> Path:
    """Inputs of every kind, good and bad, in one folder (never written by the tests)."""
    from mehs.capture.scene import make_scene
    from mehs.capture.sensor import SensorModel
    from mehs.capture.simulate import simulate_bracket, write_simulated_scene
    from mehs.dataset.build import build_from_hs
    from mehs.io.exr import write_exr_rgb
    from mehs.rgb import WAVELENGTHS_31

    r = tmp_path_factory.mktemp("fx")
    rng = np.random.default_rng(0)
    _cube(r / "cube.hdr", rng.random((6, 5, 61), dtype=np.float32), np.linspace(400, 1000, 61))
    _cube(r / "ir3.hdr", rng.random((6, 5, 3), dtype=np.float32), [900.0, 950.0, 1000.0])
    bad = rng.random((6, 5, 31), dtype=np.float32)
    bad[1, 1, 3], bad[2, 2, 2] = np.nan, np.inf
    _cube(r / "nan.hdr", bad, WAVELENGTHS_31)
    _cube(r / "trunc.hdr", rng.random((6, 5, 31), dtype=np.float32), WAVELENGTHS_31)
    raw = next(p for p in r.iterdir() if p.stem == "trunc" and p.suffix != ".hdr")
    raw.write_bytes(raw.read_bytes()[:100])
    (r / "empty.hdr").write_bytes(b"")
    (r / "notes.txt").write_text("not a cube\n")
    (r / "adir").mkdir()
    write_exr_rgb(r / "rgb.exr", rng.random((6, 5, 3)).astype(np.float32))
    (r / "bad.exr").write_bytes(b"\x76\x2f\x31\x01garbage")
    for sid, lines in (("s1", 16), ("s_short", 12)):
        scene = make_scene("colorchecker", lines, 16, seed=7)
        sim = simulate_bracket(scene, SensorModel(seed=3), (0.05, 0.4, 3.2), seed=0)
        write_simulated_scene(sim, r / sid, scene_id=sid)
    cubes = r / "cubes"
    cubes.mkdir()
    for i in range(3):
        _cube(cubes / f"c{i}.hdr", rng.random((8, 8, 31), dtype=np.float32), WAVELENGTHS_31)
    build_from_hs([cubes], r / "ds", workers=1, progress=False)
    return r


def _snapshot(root: Path) -> dict[str, tuple[int, int]]:
    return {str(p): (p.stat().st_size, p.stat().st_mtime_ns) for p in root.rglob("*")}


@pytest.fixture
def check(fx, tmp_path, capsys):
    """``check(argv, *names, rc=2)``: run ``mehs argv``; assert a clean, named failure.

    ``FX``/``OUT`` in an argument stand for the fixture folder and a fresh
    output folder; afterwards the fixtures must be untouched and ``OUT`` must
    not exist (nothing partial written).
    """
    out = tmp_path / "out"

    def run(argv, *names, rc=2, allow_out=False, strict=True):
        argv = [a.replace("FX", str(fx)).replace("OUT", str(out)) for a in argv]
        before = _snapshot(fx)
        code = main(argv)
        err = capsys.readouterr().err
        assert code == rc, err
        assert "Traceback" not in err
        if rc == 2:  # strict: nothing (a log line, a progress bar) happened before the check
            first = err if strict else err.strip().splitlines()[-1]
            assert first.startswith("mehs: error:"), err
        for n in names:
            assert n.replace("FX", str(fx)).replace("OUT", str(out)) in err, err
        assert _snapshot(fx) == before, "inputs were changed or files added beside them"
        if not allow_out:
            assert not out.exists(), sorted(str(p) for p in out.rglob("*"))
        return err

    return run


# ------------------------------------------------------------------ info / resample / rgb / export

@pytest.mark.parametrize("name, problem", [
    ("nope.hdr", "does not exist"),
    ("adir", "not a Specim IQ capture"),
    ("empty.hdr", "not an ENVI header"),
    ("trunc.hdr", "truncated"),
    ("bad.exr", "OpenEXR"),
    ("notes.txt", "no ENVI header"),
])
def test_info_bad_files(check, name, problem):
    check(["info", f"FX/{name}"], f"FX/{name.split('.')[0]}", problem)


def test_info_bad_options(check):
    check(["info", "FX/cube.hdr", "--lines", "-3"], "--lines")
    check(["info", "FX/cube.hdr", "--saturation", "-1"], "--saturation")


@pytest.mark.parametrize("src, args, names", [
    ("trunc.hdr", [], ["FX/trunc", "truncated"]),
    ("nan.hdr", [], ["FX/nan.hdr", "NaN"]),
    ("rgb.exr", [], ["FX/rgb.exr", "no spectral channels"]),
    ("ir3.hdr", [], ["FX/ir3.hdr", "no source coverage"]),
    ("cube.hdr", ["--bands", "1200:1300:10"], ["FX/cube.hdr", "no source coverage"]),
    ("cube.hdr", ["--bands", "abc"], ["'abc'"]),
    ("cube.hdr", ["--bands", "500,500,600"], ["duplicate"]),
    ("cube.hdr", ["--fwhm", "-5"], ["FWHM"]),
])
def test_resample_bad_input(check, src, args, names):
    check(["resample", f"FX/{src}", "OUT/r.hdr", *args], *names)


def test_resample_never_overwrites_its_input_or_writes_through_a_file(check):
    check(["resample", "FX/cube.hdr", "FX/cube.hdr", "--force"], "FX/cube.hdr", "overwrite the input")
    check(["resample", "FX/cube.hdr", "FX/ir3.hdr"], "FX/ir3.hdr", "--force")
    check(["resample", "FX/cube.hdr", "FX/cube.hdr/x.hdr"], "FX/cube.hdr is a file")


@pytest.mark.parametrize("src, args, names", [
    ("ir3.hdr", [], ["FX/ir3.hdr", "no source coverage"]),
    ("ir3.hdr", ["--no-resample"], ["FX/ir3.hdr", "360..830"]),
    ("nan.hdr", [], ["FX/nan.hdr", "NaN"]),
    ("empty.hdr", [], ["FX/empty.hdr"]),
    ("cube.hdr", ["--key", "0"], ["key"]),  # used to leave hdr_rgb.exr + ldr_rgb.png behind
    ("cube.hdr", ["--ldr-exposure", "-1"], ["exposure"]),
])
def test_rgb_bad_input(check, src, args, names):
    check(["rgb", f"FX/{src}", "--out", "OUT/x", *args], *names)


def test_rgb_and_export_out_is_a_file(check):
    check(["rgb", "FX/cube.hdr", "--out", "FX/cube.hdr"], "FX/cube.hdr", "not a folder")
    check(["export", "FX/cube.hdr", "--out", "FX/notes.txt"], "FX/notes.txt", "not a folder")


@pytest.mark.parametrize("src, args, names", [
    ("nan.hdr", [], ["FX/nan.hdr", "NaN"]),  # used to leave band_000/001.exr behind
    ("ir3.hdr", ["--bands", "400:700:10"], ["FX/ir3.hdr", "coverage"]),
    ("cube.hdr", ["--prefix", "../evil"], ["prefix"]),
    ("rgb.exr", [], ["FX/rgb.exr"]),
])
def test_export_bad_input(check, src, args, names):
    check(["export", f"FX/{src}", "--out", "OUT/x", *args], *names)


def test_export_half_overflow_in_a_late_band_writes_nothing(check, fx, tmp_path):
    from mehs.rgb import WAVELENGTHS_31

    d = np.ones((4, 4, 31), np.float32)
    d[..., 20:] = 1e6  # bands 0..19 would have been written before the writer refused
    big = _cube(tmp_path / "big.hdr", d, WAVELENGTHS_31)
    check(["export", str(big), "--out", "OUT/x", "--half"], str(big), "half-float range")


# ------------------------------------------------------------------ fuse

@pytest.mark.parametrize("args, names", [
    (["FX/nope"], ["FX/nope", "does not exist"]),
    (["FX/cube.hdr"], ["FX/cube.hdr", "not a scene folder"]),
    (["FX/s1/exposures/0_0.05ms"], ["FX/s1/exposures/0_0.05ms", "two or more"]),
    (["FX/s1/exposures/0_0.05ms", "FX/s1/exposures/0_0.05ms"], ["FX/s1/exposures/0_0.05ms", "distinct"]),
    (["FX/s1/exposures/0_0.05ms", "FX/s_short/exposures/1_0.4ms"], ["FX/s_short", "shapes differ"]),
    (["FX/s1/exposures/0_0.05ms", "FX/adir"], ["FX/adir"]),
    (["FX/s1", "--lambda", "-1"], ["lambda"]),
    (["FX/s1", "--samples", "0"], ["samples"]),
    (["FX/s1", "--reference", "9"], ["FX/s1", "0..2"]),
    (["FX/s1", "--response", "FX/nope.json"], ["FX/nope.json", "not found"]),
    (["FX/s1", "--calibration", "-1"], ["calibration"]),
])
def test_fuse_bad_brackets_and_options(check, args, names):
    check(["fuse", *args, "--out", "OUT/f"], *names)


def test_fuse_out_must_be_a_new_folder_outside_the_scene(check):
    check(["fuse", "FX/s1", "--out", "FX/cube.hdr"], "FX/cube.hdr", "not a folder")
    check(["fuse", "FX/s1", "--out", "FX/s1"], "FX/s1", "inside the input")
    check(["fuse", "FX/s1", "--out", "FX/cube.hdr/sub"], "FX/cube.hdr is a file")


@pytest.fixture
def damaged_scene(fx, tmp_path):
    def make(name, mutate):
        d = tmp_path / name
        shutil.copytree(fx / "s1", d)
        mutate(d)
        return d
    return make


def test_fuse_verifies_raw_files(check, damaged_scene):
    d = damaged_scene("trunc", lambda d: [p.write_bytes(p.read_bytes()[:50])
                                          for p in d.glob("exposures/1_*/capture/*.raw")])
    check(["fuse", str(d), "--out", "OUT/f"], "1_0.4ms.raw", "SHA-256")
    check(["fuse", str(d), "--out", "OUT/f", "--verify", "none"], "1_0.4ms.raw", "truncated")


# ------------------------------------------------------------------ build

@pytest.mark.parametrize("args, names", [
    (["FX/nope"], ["FX/nope"]),
    (["FX/cube.hdr"], ["FX/cube.hdr", "expected a scene folder"]),
    (["FX/s1", "--workers", "-2"], ["--workers"]),
    (["FX/s1", "--splits", "0.5,0.5,0.5"], ["splits"]),
    (["FX/s1", "--max-ghost", "-1"], ["max_ghost_fraction"]),
    (["FX/s1", "--max-saturated", "nan"], ["max_saturated_fraction"]),
    (["FX/s1", "--fwhm", "-1"], ["FWHM"]),
    (["FX/s1", "--response", "FX/notes.txt"], ["FX/notes.txt", "response curve"]),
])
def test_build_bad_options_fail_before_any_scene(check, args, names):
    check(["build", *args, "--out", "OUT/d", "-q"], *names)


def test_build_unreachable_scheduler_leaves_no_dataset_folder(check):
    pytest.importorskip("distributed")
    check(["build", "FX/s1", "--out", "OUT", "-q", "--scheduler", "bogus"], "bogus", "Dask")


def test_build_out_must_be_a_folder_outside_the_scenes(check):
    check(["build", "FX/s1", "--out", "FX/cube.hdr", "-q"], "FX/cube.hdr", "not a folder")
    check(["build", "FX/s1", "--out", "FX/s1", "-q"], "FX/s1", "inside the input")


def test_build_names_a_damaged_scene_json(check, damaged_scene):
    d = damaged_scene("listjson", lambda d: (d / "scene.json").write_text("[1]"))
    err = check(["build", str(d), "--out", "OUT/d", "-q"], "scene.json", rc=1, allow_out=True)
    assert "AttributeError" not in err


# ------------------------------------------------------------------ report / train-baseline / evaluate

def test_report_never_replaces_the_manifest(check, fx):
    check(["report", "FX/ds", "--out", "FX/ds/manifest.json"], "FX/ds/manifest.json", ".html")
    check(["report", "FX/ds", "--out", "FX/adir"], "FX/adir", "not a folder")
    check(["report", "FX/adir"], "FX/adir", "neither a dataset")


def test_train_baseline_never_replaces_a_non_model_file(check):
    check(["train-baseline", "FX/ds", "--out", "FX/ds/manifest.json"], "FX/ds/manifest.json",
          "not a mehs-ssr-regression/1 model")
    check(["train-baseline", "FX/ds", "--out", "FX/adir"], "FX/adir", ".json or .npz")
    check(["train-baseline", "FX/ds", "--out", "OUT/m.json", "--ridge", "-1"], "ridge")
    check(["train-baseline", "FX/ds", "--out", "OUT/m.json", "--samples", "0"], "n_samples")
    check(["train-baseline", "FX/ds", "--out", "OUT/m.json", "--split", "nope"],
          "FX/ds/manifest.json", "'nope'")


@pytest.fixture
def damaged_dataset(fx, tmp_path):
    def make(name, mutate):
        d = tmp_path / name
        shutil.copytree(fx / "ds", d)
        mutate(d)
        return d
    return make


@pytest.mark.parametrize("name, mutate, names", [
    ("badjson", lambda d: (d / "manifest.json").write_text('{"format": "mehs-dataset/1", "scenes": ['),
     ["manifest.json", "cannot read the manifest"]),
    ("notdict", lambda d: (d / "manifest.json").write_text("[1, 2]"), ["manifest.json"]),
    ("scenes", lambda d: (d / "manifest.json").write_text('{"format": "mehs-dataset/1", "scenes": "x"}'),
     ["manifest.json", "'scenes'"]),
    ("missing", lambda d: (d / "scenes" / "c1" / "hdr_rgb.exr").unlink(), ["c1/hdr_rgb.exr", "missing"]),
])
def test_evaluate_damaged_dataset_writes_nothing(check, damaged_dataset, name, mutate, names):
    d = damaged_dataset(name, mutate)
    check(["evaluate", str(d), "--out", "OUT/e", "-m", "smits", "--split", "all"], *names)


@pytest.mark.parametrize("text, problem", [
    ("{bad", "cannot read evaluation results"),
    ("[1]", "not an evaluation results file"),
    ('{"format": "mehs-evaluation/1", "rows": "x"}', "'rows'"),  # was a TypeError traceback
])
def test_report_damaged_evaluation(check, tmp_path, text, problem):
    ev = tmp_path / "ev"
    ev.mkdir()
    (ev / "evaluation.json").write_text(text)
    check(["report", str(ev)], str(ev / "evaluation.json"), problem)
    assert not (ev / "report.html").exists()


@pytest.mark.parametrize("text, problem", [
    ("{oops", "JSON"),
    ('{"format": "mehs-dataset/1", "scenes": [1, 2]}', "scene entry #1"),  # was a TypeError
    ('{"format": "mehs-dataset/1", "scenes": [{"status": "pass"}]}', "scene entry #1"),  # KeyError
])
def test_report_and_build_damaged_manifest(check, damaged_dataset, text, problem):
    d = damaged_dataset("bad", lambda d: (d / "manifest.json").write_text(text))
    check(["report", str(d)], "manifest.json", problem)
    assert not (d / "report.html").exists()
    before = (d / "manifest.json").read_text()
    check(["build", "FX/cubes", "--from-hs", "--out", str(d), "-q"], "manifest.json", problem)
    assert (d / "manifest.json").read_text() == before


@pytest.mark.parametrize("args, names", [
    (["-m", "nope"], ["unknown model 'nope'"]),
    (["-m", "FX/nope.onnx"], ["FX/nope.onnx"]),
    (["-m", "smits", "--crop", "-1"], ["crop"]),
    (["-m", "smits", "--split", "nope"], ["FX/ds/manifest.json", "'nope'"]),
    (["-m", "smits", "--timing", "--timing-size", "0x5"], ["--timing-size"]),
    (["-m", "smits", "--input", "nope"], ["nope"]),
])
def test_evaluate_bad_options(check, args, names):
    check(["evaluate", "FX/ds", "--out", "OUT/e", *args], *names)


def test_evaluate_out_is_a_file(check):
    check(["evaluate", "FX/ds", "--out", "FX/cube.hdr", "-m", "smits"], "FX/cube.hdr", "not a folder")


def test_train_ssr_bad_options(check):
    pytest.importorskip("torch")
    check(["train-ssr", "FX/nope", "--out", "OUT/t"], "FX/nope")
    check(["train-ssr", "FX/ds", "--out", "OUT/t", "--epochs", "0"], "--epochs")
    check(["train-ssr", "FX/ds", "--out", "OUT/t", "--lr-max", "-1", "--quiet"], "lr_max")
    check(["train-ssr", "FX/ds", "--out", "OUT/t", "--param", "growth=-3", "--quiet"], "growth")
    check(["train-ssr", "FX/ds", "--out", "OUT/t", "--param", "growth=0", "--quiet"], "growth")
    check(["train-ssr", "FX/ds", "--out", "OUT/t", "--arch", "unet", "--quiet"], "'unet'", "mstpp")
    check(["train-ssr", "FX/ds", "--out", "OUT/t", "--reinhard-scale", "0", "--quiet"],
          "--reinhard-scale")
    check(["train-ssr", "FX/ds", "--out", "FX/cube.hdr", "--epochs", "1", "--quiet"],
          "FX/cube.hdr", "not a folder")


def test_demo_bad_options(check):
    check(["demo", "--scenes", "0", "--out", "OUT/d"], "--scenes")
    check(["demo", "--size", "nope", "--out", "OUT/d"], "--size")
    check(["demo", "--workers", "-1", "--out", "OUT/d"], "--workers")
    check(["demo", "--out", "FX/ds"], "FX/ds", "not a mehs demo folder")
    check(["demo", "--out", "FX/cube.hdr/d"], "FX/cube.hdr")


# ------------------------------------------------------------------ capture / sim-device

SIM = ["capture", "--simulate", "--size", "16", "--no-progress"]


@pytest.mark.parametrize("args, names", [
    (["--times", "5,1,2"], ["ascending"]),
    (["--times", "5,5,20"], ["ascending"]),
    (["--times", "0,2"], ["positive"]),
    (["--times", "nan,2"], ["positive"]),
    (["--times", "abc"], ["--times"]),
    (["--times", "0.05,0.4", "--pitch", "-1"], ["pitch"]),  # used to leave scene.json behind
    (["--times", "0.05,0.4", "--timeout", "0"], ["timeout"]),
    (["--times", "0.05,0.4", "--dark-lines", "0"], ["dark_lines"]),
    (["--times", "0.05,0.4", "--scene", "nope"], ["'nope'"]),
    (["--times", "0.05,0.4", "--faults", "zzz"], ["'zzz'"]),
    (["--resume"], ["OUT/sc", "no scene.json"]),
])
def test_capture_bad_options(check, args, names):
    check([*SIM, "--out", "OUT/sc", *args], *names)


def test_capture_never_overwrites_a_raw_capture(check):
    check([*SIM, "--out", "FX/s1", "--times", "0.05,0.4"], "FX/s1", "never overwritten")
    check([*SIM, "--out", "FX/cube.hdr", "--times", "0.05,0.4"], "FX/cube.hdr", "not a folder")


def test_capture_device_that_never_answers(check):
    srv = socket.socket()
    srv.bind(("127.0.0.1", 0))
    srv.listen(2)
    conns = []

    def accept():
        while True:
            try:
                conns.append(srv.accept()[0])
            except OSError:
                return

    threading.Thread(target=accept, daemon=True).start()
    url = f"socket://127.0.0.1:{srv.getsockname()[1]}"
    try:
        check(["capture", "--stage", url, "--camera", url, "--out", "OUT/sc", "--times", "1,2",
               "--timeout", "0.2"], url, "timeout", strict=False)
    finally:
        srv.close()
        for c in conns:
            c.close()


def test_capture_port_that_does_not_exist(check, fx):
    check(["capture", "--stage", "FX/nope-tty", "--camera", "FX/nope-tty", "--out", "OUT/sc",
           "--times", "1,2", "--timeout", "0.2"], "FX/nope-tty", "cannot open port")


def test_sim_device_bad_scene_and_ports(check):
    check(["sim-device", "--scene", "nope"], "'nope'")
    check(["sim-device", "--port", "70000"], "0..65535")  # was an OverflowError traceback
    busy = socket.socket()
    busy.bind(("127.0.0.1", 0))
    busy.listen(1)
    try:
        port = busy.getsockname()[1]
        check(["sim-device", "--port", str(port)], f"127.0.0.1:{port}", "in use")
    finally:
        busy.close()


# ------------------------------------------------------------------ Ctrl-C

def test_keyboard_interrupt_leaves_no_partial_file(fx, tmp_path, capsys, monkeypatch):
    import mehs.io.atomic as atomic

    def interrupted(src, dst):
        raise KeyboardInterrupt

    monkeypatch.setattr(atomic.os, "replace", interrupted)
    out = tmp_path / "out"
    assert main(["resample", str(fx / "cube.hdr"), str(out / "r.hdr")]) == 130
    err = capsys.readouterr().err
    assert "interrupted" in err and "Traceback" not in err
    assert [p.name for p in out.iterdir()] == [] if out.exists() else True


# ------------------------------------------------------------------ real processes

@pytest.mark.parametrize("argv, name", [
    (["info", "FX/trunc.hdr"], "FX/trunc"),
    (["rgb", "FX/ir3.hdr", "--out", "OUT", "--no-resample"], "FX/ir3.hdr"),
])
def test_subprocess_exit_status_and_stderr(fx, tmp_path, argv, name):
    argv = [a.replace("FX", str(fx)).replace("OUT", str(tmp_path / "o")) for a in argv]
    env = {**os.environ, "PYTHONPATH": str(Path(__file__).resolve().parents[1])}
    p = subprocess.run([sys.executable, "-m", "mehs", *argv], capture_output=True, text=True,
                       env=env, timeout=60)
    assert p.returncode == 2, p.stderr
    assert p.stderr.startswith("mehs: error:") and name.replace("FX", str(fx)) in p.stderr
    assert "Traceback" not in p.stderr
    assert not (tmp_path / "o").exists()
