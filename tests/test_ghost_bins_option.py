"""The bin width of the ghost test's χ² statistic as a user sets it: `mehs fuse --ghost-bins`,
`mehs build --ghost-bins`, ``fuse_bracket(ghost_bins=)`` (the merge's ``consistency_bins``).

Bins of adjacent bands (the default for dense spectra) flag more weakly moving pixels but
let a change whose sign flips within a bin cancel there; a lab imaging narrow spectral
features that move across each other asks for 1. What it changes is the statistic only:
the radiance is the same to the bit, and the scene key names the width (or, left at auto,
the rule that auto follows).
"""

from __future__ import annotations

import json

import numpy as np
import pytest

from mehs.errors import InputError
from mehs.synthesis.merge_types import consistency_bins_value

SIZE = 24
TIMES_MS = (0.05, 0.4, 3.2)


@pytest.fixture(scope="module")
def moving_scene(tmp_path_factory):
    """A small simulated scene of the camera's 204 bands with a moving object."""
    from mehs.capture.scene import make_scene
    from mehs.capture.sensor import SensorModel
    from mehs.capture.simulate import simulate_bracket, write_simulated_scene

    scene = make_scene("colorchecker", SIZE, SIZE, motion=True, seed=7)
    sim = simulate_bracket(scene, SensorModel(seed=3), TIMES_MS, seed=0)
    return write_simulated_scene(sim, tmp_path_factory.mktemp("scene") / "mv", scene_id="mv")


@pytest.mark.parametrize("given, expected", [("auto", "auto"), (" AUTO ", "auto"), ("4", 4),
                                             (" 2 ", 2), (1, 1), (np.int64(8), 8)])
def test_a_bin_width_is_auto_or_a_whole_number_of_bands(given, expected):
    assert consistency_bins_value(given) == expected


@pytest.mark.parametrize("bad", [0, -1, "0", "x", "4.0", "", 2.5, True, None, np.float64(4.0),
                                 "٤", "４", "9" * 5000])
def test_anything_else_is_refused_naming_the_option(bad):
    with pytest.raises(InputError, match="--ghost-bins must be 'auto' or a whole number"):
        consistency_bins_value(bad, what="--ghost-bins")


def test_fuse_records_the_width_and_the_radiance_does_not_change(moving_scene):
    from mehs.synthesis.bracket import load_bracket
    from mehs.synthesis.fuse import fuse_bracket

    b = load_bracket(moving_scene)
    assert b.shape[2] >= 100
    auto = fuse_bracket(b, response="linear", noise="recorded")
    one = fuse_bracket(b, response="linear", noise="recorded", ghost_bins=1)
    eight = fuse_bracket(b, response="linear", noise="recorded", ghost_bins="8")
    assert (auto.summary["ghost_chi2_bins"], one.summary["ghost_chi2_bins"],
            eight.summary["ghost_chi2_bins"]) == (4, 1, 8)
    for r in (one, eight):
        assert np.array_equal(r.radiance.data, auto.radiance.data)
    # the statistic is the one asked for: the moving object is found either way
    assert auto.summary["ghost_fraction"] > 0 and one.summary["ghost_fraction"] > 0


def test_fuse_bins_the_statistic_of_a_weighted_merge_too(moving_scene):
    """Robertson's merge of a linear sensor has its binned statistic: auto takes it for the
    camera's 204 bands, the radiance is the per-band fusion's, the object is found."""
    from mehs.synthesis.bracket import load_bracket
    from mehs.synthesis.fuse import fuse_bracket

    b = load_bracket(moving_scene)
    auto = fuse_bracket(b, method="robertson", response="linear", noise="recorded")
    one = fuse_bracket(b, method="robertson", response="linear", noise="recorded", ghost_bins=1)
    assert (auto.summary["ghost_chi2_bins"], one.summary["ghost_chi2_bins"]) == (4, 1)
    assert np.array_equal(auto.radiance.data, one.radiance.data)
    assert auto.summary["ghost_fraction"] > 0


def test_fuse_refuses_bins_for_a_merge_without_them_before_any_work(moving_scene, monkeypatch):
    from mehs.synthesis import fuse as fuse_mod
    from mehs.synthesis.bracket import load_bracket

    def no_work(*a, **k):
        raise AssertionError("the response was chosen before the refusal")

    monkeypatch.setattr(fuse_mod, "choose_response", no_work)
    b = load_bracket(moving_scene)
    with pytest.raises(InputError, match=r"--ghost-bins\) = 2 needs a linear sensor, and the "
                                         "response asked for is 'debevec'"):
        fuse_mod.fuse_bracket(b, response="debevec", ghost_bins=2)
    with pytest.raises(InputError, match=r"ghost_bins \(--ghost-bins\) must be"):
        fuse_mod.fuse_bracket(b, ghost_bins=0)


def test_fuse_refuses_bins_once_the_response_proves_non_linear(moving_scene, monkeypatch):
    """`auto` may recover a curve: then the merge has no binned statistic, said before it
    runs, naming the option."""
    from mehs.synthesis import fuse as fuse_mod
    from mehs.synthesis.bracket import load_bracket
    from mehs.synthesis.response import ResponseCurve

    real = fuse_mod.choose_response
    bent = ResponseCurve(np.log(np.maximum(np.arange(4096.0), 0.5)) * 1.01, 12, "debevec")

    def recovered(*a, **k):
        curve, info, probe = real(*a, **k)
        return bent, info, probe

    monkeypatch.setattr(fuse_mod, "choose_response", recovered)
    monkeypatch.setattr(fuse_mod, "merge_bracket", lambda *a, **k: pytest.fail("merged"))
    with pytest.raises(InputError, match="needs a linear sensor, and this bracket's response "
                                         "is 'debevec'"):
        fuse_mod.fuse_bracket(load_bracket(moving_scene), ghost_bins=4)


def test_cli_fuse_takes_the_option(moving_scene, tmp_path, capsys):
    from mehs.cli import main

    out = tmp_path / "f1"
    assert main(["fuse", str(moving_scene), "--out", str(out), "--ghost-bins", "1",
                 "--response", "linear"]) == 0
    assert json.loads((out / "summary.json").read_text())["ghost_chi2_bins"] == 1
    for args, says in ((["--ghost-bins", "none"], "--ghost-bins must be 'auto' or a whole"),
                       (["--ghost-bins", "4", "--response", "debevec"],
                        "--ghost-bins) = 4 needs a linear sensor")):
        capsys.readouterr()
        assert main(["fuse", str(moving_scene), "--out", str(tmp_path / "f2"), *args]) != 0
        assert says in capsys.readouterr().err
        assert not (tmp_path / "f2" / "summary.json").exists()


def test_build_params_normalise_the_width_and_refuse_what_the_merge_cannot():
    from mehs.dataset.scene_task import BuildParams

    assert BuildParams(ghost_bins="4").ghost_bins == 4 == BuildParams(ghost_bins=4).ghost_bins
    assert BuildParams().ghost_bins == "auto"
    assert BuildParams(method="debevec", ghost_bins=1).ghost_bins == 1
    assert BuildParams(method="debevec", ghost_bins=4, ghosts="off").ghost_bins == 4
    assert BuildParams(method="robertson", ghost_bins=4).ghost_bins == 4
    with pytest.raises(InputError, match=r"ghost_bins \(--ghost-bins\) must be"):
        BuildParams(ghost_bins="wide")


def test_cli_build_names_the_option_and_refuses_a_non_linear_curve_up_front(
        moving_scene, tmp_path, capsys):
    from mehs.cli import main
    from mehs.synthesis.response import ResponseCurve

    bent = ResponseCurve(np.log(np.maximum(np.arange(4096.0), 0.5)), 12, "debevec")
    curve = bent.save(tmp_path / "bent.json")
    for args, says in ((["--ghost-bins", "wide"], "--ghost-bins must be 'auto' or a whole"),
                       (["--ghost-bins", "2", "--response", str(curve)],
                        "--ghost-bins) = 2 needs a linear sensor, and this response curve "
                        "is 'debevec'"),
                       (["--from-hs", "--ghost-bins", "x"], "--ghost-bins must be")):
        capsys.readouterr()
        assert main(["build", str(moving_scene), "--out", str(tmp_path / "ds"), "-q",
                     *args]) != 0
        assert says in capsys.readouterr().err
        assert not (tmp_path / "ds" / "manifest.json").exists()


def test_the_scene_key_names_the_width_or_the_rule_of_auto(moving_scene):
    from mehs.dataset.scene_list import collect_scenes
    from mehs.dataset.scene_task import BuildParams, SceneTask, _params_for_key

    (src,) = collect_scenes([moving_scene])

    def key_params(**kw):
        return _params_for_key(SceneTask(src, "ds", BuildParams(**kw)))

    assert key_params(ghost_bins=1)["ghost_bins"] == 1
    assert key_params(ghost_bins="4") == key_params(ghost_bins=4) != key_params()
    # what "auto" gives changed in session 35 (bins for the weighted merges) and 36 (bins
    # for 4 to 16 exposures): scenes built with it rebuild once, under a key that names
    # the rule (next test); scenes built without the ghost test keep their keys
    for method in ("poisson", "debevec", "robertson", "inverse-variance"):
        assert key_params(method=method)["ghost_bins"] not in (None, "auto", 1, 4)
        assert "ghost_bins" not in key_params(method=method, ghosts="off")
    assert key_params(method="robertson") != key_params(method="robertson", ghost_bins=1)


def test_auto_keeps_session_35s_key_for_brackets_it_merges_as_then(moving_scene, tmp_path):
    """Session 36 changed what auto gives for brackets of 4 to 16 exposures only: a
    bracket of at most 3 keeps its key (no rebuild), one of more gets the new rule. The
    count is the bracket's complete exposures (a scene folder) or its folders (Specim IQ)."""
    import shutil

    from mehs.capture.scene import make_scene
    from mehs.capture.sensor import SensorModel
    from mehs.capture.simulate import simulate_bracket, write_simulated_scene
    from mehs.dataset.scene_list import SceneSource, collect_scenes
    from mehs.dataset.scene_task import (AUTO_BINS_RULE, AUTO_BINS_RULE_35, BuildParams,
                                         SceneTask, _params_for_key, bracket_exposures)

    def rule(src):
        return _params_for_key(SceneTask(src, "ds", BuildParams()))["ghost_bins"]

    (three,) = collect_scenes([moving_scene])
    assert bracket_exposures(three) == 3 and rule(three) == AUTO_BINS_RULE_35
    scene = make_scene("colorchecker", 8, 8, motion=True, seed=7)
    sim = simulate_bracket(scene, SensorModel(seed=3), (0.05, 0.2, 0.8, 3.2, 12.8), seed=0)
    five_dir = write_simulated_scene(sim, tmp_path / "five", scene_id="five")
    (five,) = collect_scenes([five_dir])
    assert bracket_exposures(five) == 5 and rule(five) == AUTO_BINS_RULE
    # an exposure the capture did not finish is not merged (allow_partial) nor counted
    partial_dir = tmp_path / "partial"
    shutil.copytree(five_dir, partial_dir)
    meta = json.loads((partial_dir / "scene.json").read_text())
    for exp in meta["exposures"][3:]:
        exp["status"] = "incomplete"
    (partial_dir / "scene.json").write_text(json.dumps(meta))
    (partial,) = collect_scenes([partial_dir])
    assert bracket_exposures(partial) == 3 and rule(partial) == AUTO_BINS_RULE_35
    for n, want in ((3, AUTO_BINS_RULE_35), (4, AUTO_BINS_RULE)):
        iq = SceneSource("iq", "specim", tuple(f"/nowhere/{k}" for k in range(n)))
        assert rule(iq) == want


def test_build_rebuilds_a_scene_with_the_width_it_is_given(moving_scene, tmp_path):
    from mehs.dataset.build import build_dataset
    from mehs.dataset.quality import QualityRules
    from mehs.synthesis.response import ResponseCurve

    curve = ResponseCurve.linear(12).save(tmp_path / "linear.json")
    ds = tmp_path / "ds"
    commits = []
    kw = dict(workers=1, rules=QualityRules(), progress=False, response=curve,
              on_commit=commits.append)
    build_dataset([moving_scene], ds, **kw)
    fusion = ds / "scenes" / "mv" / "fusion.json"
    assert json.loads(fusion.read_text())["ghost_chi2_bins"] == 4
    build_dataset([moving_scene], ds, ghost_bins="1", **kw)
    assert [c["id"] for c in commits] == ["mv", "mv"]            # the key changed: rebuilt
    assert json.loads(fusion.read_text())["ghost_chi2_bins"] == 1
