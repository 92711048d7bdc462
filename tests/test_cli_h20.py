"""A new user's first hour with the command line: help that states what it does, and clear
errors on the common mistakes (a lone file for a bracket, a typo in a scene kind, a missing
folder), checked the way the user meets them, through ``mehs.cli.main``."""

from __future__ import annotations

import argparse
import json
import re
from pathlib import Path

import numpy as np
import pytest

from mehs.cli import COMMANDS, build_parser, main

README = Path(__file__).resolve().parents[1] / "README.md"


def _subparsers() -> dict[str, argparse.ArgumentParser]:
    parser = build_parser()
    sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    return dict(sub.choices)


# ------------------------------------------------------------------ help text

def test_readme_command_list_is_what_mehs_help_prints():
    """The README's ``mehs --help`` block is the parser's one-line help of every command
    (train-ssr said "the HDR SSR network" after it had become the zoo's trainer)."""
    text = README.read_text(encoding="utf-8")
    block = text.split("$ mehs --help\n", 1)[1].split("```", 1)[0]
    shown = {}
    for line in block.splitlines():
        m = re.match(r"\s{4}(\S+)\s+(.+)$", line)
        if m:
            shown[m[1]] = m[2].strip()
    assert shown == {name: help_ for name, _, help_ in COMMANDS}


def test_every_option_with_a_default_states_it():
    """``--help`` names the default of every option that has one (fuse --response/--ghosts,
    capture --dark-lines/--timeout, paper --seed, ... did not)."""
    missing = []
    for name, sp in _subparsers().items():
        for a in sp._actions:
            if not a.option_strings or isinstance(a, (argparse._HelpAction, argparse._VersionAction,
                                                      argparse._StoreTrueAction,
                                                      argparse._StoreFalseAction)):
                continue
            if a.default is None or a.default is False or a.default in ([], ""):
                continue
            if "default" not in (a.help or "").lower():
                missing.append(f"mehs {name} {a.option_strings[0]} (default {a.default!r})")
    assert not missing, missing


def test_help_matches_what_the_options_do():
    sp = _subparsers()
    helps = {(n, a.option_strings[0]): a.help or "" for n, p in sp.items() for a in p._actions
             if a.option_strings}
    # the demo fuses every scene with a ladder's curve; --known-response replaces that curve
    assert "ladder" in helps[("demo", "--known-response")]
    # references are stored line by line since scene folders keep the lines read
    assert "averaged per" not in helps[("capture", "--dark-lines")]
    assert "stored as read" in helps[("capture", "--dark-lines")]
    # build lists its merge estimators as fuse does
    assert "inverse-variance" in sp["build"].format_help()


# ------------------------------------------------------------------ errors on common mistakes

@pytest.fixture(scope="module")
def scene(tmp_path_factory) -> Path:
    from mehs.capture.scene import make_scene
    from mehs.capture.sensor import SensorModel
    from mehs.capture.simulate import simulate_bracket, write_simulated_scene

    root = tmp_path_factory.mktemp("h20")
    sim = simulate_bracket(make_scene("colorchecker", 12, 12, seed=1), SensorModel(seed=2),
                           (0.05, 0.4, 3.2), seed=0)
    write_simulated_scene(sim, root / "s1", scene_id="s1")
    return root / "s1"


def _fails(capsys, argv, *needles, logged: bool = False) -> str:
    code = main([str(a) for a in argv])
    err = capsys.readouterr().err
    assert code == 2, err
    # nothing before the error, unless the command logged its progress (a capture)
    said = err.strip().splitlines()[-1] if logged else err
    assert said.startswith("mehs: error:") and "Traceback" not in err, err
    for n in needles:
        assert str(n) in err, err
    return err


@pytest.mark.parametrize("command", ["fuse", "calibrate"])
def test_lone_path_that_cannot_be_a_bracket_is_named_for_what_it_is(scene, tmp_path, capsys,
                                                                    command):
    extra = ["--source", "x.csv"] if command == "calibrate" else []
    out = tmp_path / ("cal.json" if command == "calibrate" else "out")
    # the scene's own scene.json: was "not a scene folder (no scene.json)"
    err = _fails(capsys, [command, scene / "scene.json", "--out", out, *extra],
                 scene / "scene.json", "give the scene folder")
    assert str(scene) in err
    # one exposure's Specim IQ folder: a bracket needs two or more
    one = next((scene / "exposures").iterdir())
    _fails(capsys, [command, one, "--out", out, *extra], one, "one Specim IQ capture")
    # a cube file
    cube = next((one / "capture").glob("*.hdr"))
    _fails(capsys, [command, cube, "--out", out, *extra], cube, "a file, not a scene folder")
    assert not out.exists()


def test_unknown_scene_kind_lists_natural(tmp_path, capsys):
    out = tmp_path / "scene"
    _fails(capsys, ["capture", "--simulate", "--scene", "lmap", "--out", out], "'lmap'",
           "natural", "colorchecker")
    assert not out.exists()


def test_report_of_a_missing_folder_says_it_does_not_exist(tmp_path, capsys):
    _fails(capsys, ["report", tmp_path / "nope"], tmp_path / "nope", "no such folder")


def test_paper_on_a_missing_dataset_fails_before_training(tmp_path, capsys):
    out = tmp_path / "paper"
    err = _fails(capsys, ["paper", tmp_path / "nope", "--out", out, "--quick"],
                 tmp_path / "nope", "no such dataset")
    assert "training" not in err
    assert "training" not in capsys.readouterr().out
    assert not out.exists()


# ------------------------------------------------------------------ resume of a natural scene

def test_resume_hint_and_check_keep_a_natural_scenes_lighting(tmp_path, capsys):
    """A natural scene's --lighting (drawn from --seed when not given) decides the scene: the
    resume hint gave no --lighting, and a resume without it took the rest of the bracket of
    another scene (mixed lighting) into the sodium scene's folder."""
    out = tmp_path / "nat"
    err = _fails(capsys, ["capture", "--simulate", "--scene", "natural", "--lighting", "sodium",
                          "--size", "16", "--out", out, "--times", "1,10,100", "--timeout", "0.1",
                          # read 70: mid-exposure 1 (48 reads an exposure: 16 dark, 16 white, 16
                          # lines). A busy host's spurious 0.1-s timeouts add reads to exposure 0;
                          # at read 50 two of them moved the fault into exposure 0
                          "--faults", "camera:timeout@70x20", "--no-progress"],
                 "--resume", "--lighting sodium", logged=True)
    doc = json.loads((out / "scene.json").read_text())
    assert [e["status"] for e in doc["exposures"]][0] == "complete"
    assert "incomplete" in [e["status"] for e in doc["exposures"]], err
    before = (out / "scene.json").read_bytes()
    _fails(capsys, ["capture", "--resume", "--simulate", "--scene", "natural", "--size", "16",
                    "--out", out, "--no-progress"], "--lighting sodium", "mix two scenes")
    assert (out / "scene.json").read_bytes() == before


# ------------------------------------------------------------------ progress bars

@pytest.fixture(scope="module")
def cubes(tmp_path_factory) -> Path:
    from mehs.cube import SpectralCube
    from mehs.io.envi import write_envi
    from mehs.rgb import WAVELENGTHS_31

    root = tmp_path_factory.mktemp("cubes")
    rng = np.random.default_rng(0)
    for i in range(3):
        write_envi(root / f"c{i}.hdr", SpectralCube(rng.random((8, 8, 31), dtype=np.float32),
                                                    WAVELENGTHS_31), dtype=np.float32)
    return root


def test_no_progress_bars_into_a_pipe_or_log(cubes, tmp_path, capsys):
    """Commands draw bars only on a terminal, as capture and demo do: in a log each redraw
    was one more carriage-return line (build, train-baseline, evaluate)."""
    ds = tmp_path / "ds"
    for argv in (["build", "--from-hs", cubes, "--out", ds, "--splits", "0.5,0,0.5"],
                 ["train-baseline", ds, "--out", tmp_path / "reg.npz", "--samples", "100"],
                 ["evaluate", ds, "--out", tmp_path / "ev", "--split", "all"]):
        code = main([str(a) for a in argv])
        err = capsys.readouterr().err
        assert code == 0, err
        assert "%|" not in err and "\r" not in err, (argv[0], err)
