"""Warnings raised by build workers: one line per scene on stderr, kept in the manifest.

A lamp scene bracketed ×140 apart by a gamma sensor cannot determine its response curve
(tests/test_response_robust.py): fusing it raises ResponseUndeterminedWarning.
"""

import threading
import warnings
from pathlib import Path

import pytest

from mehs.dataset import manifest as mf
from mehs.dataset.scene_warnings import captured_warnings, describe

WIDE_MS = (0.01, 1.4, 197.0)
RAW = ("ResponseUndeterminedWarning", "warnings.warn", "fuse_bracket(")


@pytest.fixture(scope="module")
def wide_scenes(tmp_path_factory) -> list[Path]:
    from mehs.capture.scene import make_scene
    from mehs.capture.sensor import SensorModel
    from mehs.capture.simulate import simulate_bracket, write_simulated_scene

    root = tmp_path_factory.mktemp("wide")
    out = []
    for sid, seed in (("s1", 1), ("s2", 2)):
        scene = make_scene("lamp", 16, 16, seed=seed)
        sim = simulate_bracket(scene, SensorModel(response="gamma", seed=2), WIDE_MS, seed=3)
        out.append(write_simulated_scene(sim, root / sid, scene_id=sid))
    return out


def _recorded(entry: dict) -> list[dict]:
    return entry["provenance"]["run"].get("warnings") or []


def test_worker_warnings_are_one_line_per_scene_and_recorded(wide_scenes, tmp_path, capfd):
    from mehs.cli import main
    from mehs.dataset.report import write_report

    ds = tmp_path / "ds"
    # two worker processes: their raw warnings reached the terminal interleaved
    rc = main(["build", *map(str, wide_scenes), "--out", str(ds), "--workers", "2", "--quiet"])
    err = capfd.readouterr().err
    assert rc == 0
    lines = [ln for ln in err.splitlines() if ln.strip()]
    for sid in ("s1", "s2"):
        mine = [ln for ln in lines if ln.startswith(f"mehs build: scene {sid}: ")]
        assert len(mine) == 1, err
        assert "response curve undetermined by this bracket" in mine[0]
        assert "radiance is unreliable" in mine[0]
    assert not any(r in err for r in RAW), err
    assert lines.index(next(ln for ln in lines if "scene s1:" in ln)) < lines.index(
        next(ln for ln in lines if "scene s2:" in ln))          # by scene id
    m = mf.read_manifest(ds)
    for e in m["scenes"]:
        rec = _recorded(e)
        assert [w["category"] for w in rec] == [
            "mehs.synthesis.fuse_response.ResponseUndeterminedWarning"]
        assert rec[0]["count"] == 1
        # the condition itself is a quality flag, judged by the rules
        assert e["quality"]["response_undetermined"] is True
        assert any("response curve undetermined" in r for r in e["reasons"])
    page = write_report(ds).read_text()
    assert page.count("warning while building: response curve undetermined") == 2


def test_a_worker_shows_a_repeated_warning_for_every_scene(wide_scenes, tmp_path, capsys):
    from mehs.dataset.build import build_dataset

    # in one process (workers=1), the same scene twice: Python's default filter shows a
    # warning once per code place, so the second build lost it
    for name in ("a", "b"):
        m = build_dataset(wide_scenes[:1], tmp_path / name, workers=1, progress=False)
        assert len(_recorded(m["scenes"][0])) == 1
        err = capsys.readouterr().err
        assert err.count("mehs build: scene s1: response curve undetermined") == 1, err
        assert not any(r in err for r in RAW), err


def test_capture_is_per_thread_and_restores_the_warning_state():
    filters, show = list(warnings.filters), warnings.showwarning
    both_in, a_warned, b_done = threading.Barrier(2), threading.Event(), threading.Event()
    logs: dict[str, list] = {}
    errors = []

    def work(name: str, first: bool):
        try:
            with captured_warnings() as log:
                logs[name] = log
                both_in.wait(timeout=60)
                if first:
                    warnings.warn(f"from {name}", UserWarning)
                    warnings.warn(f"from {name}", UserWarning)   # counted, not lost
                    a_warned.set()
                    b_done.wait(timeout=60)      # b leaves first: a must keep capturing
                    warnings.warn(RuntimeWarning("late"))
                    # not the scene's: shown as the filters say (here: always), not kept
                    warnings.warn("old API", DeprecationWarning)
                else:
                    a_warned.wait(timeout=60)
                    warnings.warn(f"from {name}", UserWarning)
            if not first:
                b_done.set()
        except BaseException as exc:  # noqa: BLE001 - reported by the main thread
            errors.append(exc)
            b_done.set()

    with warnings.catch_warnings(record=True) as outside:
        warnings.simplefilter("always")
        filters, show = list(warnings.filters), warnings.showwarning
        threads = [threading.Thread(target=work, args=("a", True)),
                   threading.Thread(target=work, args=("b", False))]
        for t in threads:
            t.start()
        for t in threads:
            t.join(timeout=120)
        assert not errors, errors
        assert warnings.filters == filters and warnings.showwarning is show
        warnings.warn("after", UserWarning)            # shown the normal way again
    assert [describe(w) for w in logs["a"]] == ["UserWarning: from a (×2)",
                                                "RuntimeWarning: late"]
    assert [describe(w) for w in logs["b"]] == ["UserWarning: from b"]
    assert [str(w.message) for w in outside] == ["old API", "after"]


def test_describe_keeps_long_and_odd_records_on_one_line():
    w = {"category": "mehs.x.SomeWarning", "message": "two\nlines", "count": 3}
    assert describe(w) == "two lines (×3)"
    assert describe({"message": "m"}) == "Warning: m"
    with captured_warnings() as log:
        for i in range(30):
            warnings.warn(f"w{i}", UserWarning)
    assert len(log) == 21 and "10 more distinct warning(s), raised 10 time(s)" in log[-1]["message"]


def test_capture_keeps_the_users_filters_first():
    """-W error::RuntimeWarning still raises inside a capture; an explicit ignore still ignores."""
    with warnings.catch_warnings():
        warnings.simplefilter("error", RuntimeWarning)
        warnings.filterwarnings("ignore", message="noise", category=UserWarning)
        with captured_warnings() as log:
            warnings.warn("noise", UserWarning)
            with pytest.raises(RuntimeWarning):
                warnings.warn("overflow", RuntimeWarning)
            warnings.warn("kept", UserWarning)
        assert [w["message"] for w in log] == ["kept"]


def test_another_threads_catch_warnings_does_not_leave_the_capture_installed():
    """A library's catch_warnings entered during a capture and left after it must not keep
    the dispatcher and the 'always' filter for the rest of the process."""
    with warnings.catch_warnings():
        warnings.resetwarnings()
        warnings.simplefilter("default")
        filters, show = list(warnings.filters), warnings.showwarning
        entered, left = threading.Event(), threading.Event()

        def library():
            with warnings.catch_warnings():
                entered.set()
                left.wait(timeout=60)

        with captured_warnings():
            t = threading.Thread(target=library)
            t.start()
            entered.wait(timeout=60)
        left.set()
        t.join(timeout=60)
        # the library's exit restored what it saw (the capture's state): the dispatcher
        # left behind forwards to Python's display, so warnings are still shown, once
        with warnings.catch_warnings(record=True) as seen:
            warnings.warn("once", UserWarning)
        assert [str(w.message) for w in seen] == ["once"]
        assert warnings.filters[:len(filters)] == filters    # the user's filters first
        del show
