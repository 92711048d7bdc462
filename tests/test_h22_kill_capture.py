"""`mehs capture --simulate` killed after its last exposure, while it writes the truth.

The simulator's truth (radiance, the moved-pixel mask of a moving scene, a sphere's
certificate) is written after the exposures, piece by piece. A kill between a piece's file
and its record in scene.json, or between two pieces, used to leave a scene that
``--resume`` could not finish: it refused to overwrite the unrecorded truth file, or
skipped the pieces after the first one for good.
"""

import json

import pytest

import mehs.capture.simulate as simulate
import mehs.io.envi as envi
from mehs.cli import main

SIM = ["capture", "--simulate", "--size", "12", "--times", "1,4", "--no-progress"]


class Killed(BaseException):
    """Stands for SIGKILL: nothing after it runs (no record is written)."""


def _raw_hashes(scene):
    doc = json.loads((scene / "scene.json").read_text())
    return {rel: d for e in doc["exposures"] for rel, d in e["files"].items()}


def test_a_kill_between_the_truth_file_and_its_record_is_finished_by_resume(
        tmp_path, monkeypatch):
    out = tmp_path / "sc"
    real = envi.write_envi

    def dying(path, *a, **kw):
        real(path, *a, **kw)
        if str(path).endswith("truth/radiance.hdr"):
            raise Killed

    monkeypatch.setattr(envi, "write_envi", dying)
    with pytest.raises(Killed):
        main([*SIM, "--out", str(out)])
    monkeypatch.setattr(envi, "write_envi", real)
    raw = _raw_hashes(out)
    assert json.loads((out / "scene.json").read_text())["truth"] is None
    assert main([*SIM, "--out", str(out), "--resume"]) == 0
    doc = json.loads((out / "scene.json").read_text())
    assert doc["truth"] == "truth/radiance.hdr" and (out / doc["truth"]).is_file()
    assert _raw_hashes(out) == raw                      # the raw captures untouched


def test_a_kill_after_the_truth_before_the_moved_mask_is_finished_by_resume(
        tmp_path, monkeypatch):
    out = tmp_path / "sc"

    def dying(*a, **kw):
        raise Killed

    monkeypatch.setattr(simulate, "write_moved_mask", dying)
    with pytest.raises(Killed):
        main([*SIM, "--motion", "--out", str(out)])
    monkeypatch.undo()
    assert main([*SIM, "--motion", "--out", str(out), "--resume"]) == 0
    doc = json.loads((out / "scene.json").read_text())
    assert doc.get("truth_moved_mask") == "truth/moved_mask.png"
    assert (out / "truth" / "moved_mask.png").is_file()


def test_a_capture_killed_writing_its_first_scene_json_can_be_run_again(tmp_path):
    out = tmp_path / "sc"
    out.mkdir()
    # what atomic_path leaves when the process dies before the rename
    (out / ".scene.json.k2j9x_1a.part.json").write_text('{"format": "mehs-sc')
    assert main([*SIM, "--out", str(out)]) == 0
    assert [p.name for p in out.iterdir() if p.name.startswith(".")] == []


def test_a_second_capture_into_a_scene_folder_being_captured_is_refused(tmp_path, capsys):
    from mehs.io.lock import OutputLock

    out = tmp_path / "sc"
    # a live capture holds the folder (it has not written scene.json yet)
    with OutputLock(out, what="mehs capture"):
        assert main([*SIM, "--out", str(out)]) == 2
        assert "another 'mehs capture'" in capsys.readouterr().err
        assert [p.name for p in out.iterdir() if not p.name.startswith(".mehs")] == []
    assert main([*SIM, "--out", str(out)]) == 0      # the folder the lock made is usable


def test_an_output_path_that_is_a_file_is_named(tmp_path, capsys):
    f = tmp_path / "sc"
    f.write_text("x")
    assert main([*SIM, "--out", str(f)]) == 2
    assert "not a folder" in capsys.readouterr().err
