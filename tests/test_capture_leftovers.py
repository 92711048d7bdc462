"""Captures leave nothing behind that blocks or confuses the next step (issue 17, defects 6, 10).

A killed exposure write's ``.part-*`` folder is removed by ``--resume``; a time the camera
refuses is refused before anything is written; capture folders follow the umask; an id
``mehs build`` would refuse is refused by ``capture``; the resume hint is a command that
works; ``--simulate --resume`` with other scene options is refused.
"""

import json
import os
import shutil
import subprocess
import sys
import textwrap

import pytest

from mehs.cli import main

SIM = ["--simulate", "--size", "8", "--no-progress"]


def test_refused_time_leaves_nothing_and_allows_a_recapture(tmp_path, capsys):
    out = tmp_path / "s"
    assert main(["capture", *SIM, "--times", "1,100,99999", "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert "99999 ms" in err and "nothing was captured" in err
    assert not out.exists() or not any(out.iterdir())
    assert main(["capture", *SIM, "--times", "1,100,1000", "--out", str(out)]) == 0


@pytest.fixture()
def captured(tmp_path):
    out = tmp_path / "s"
    assert main(["capture", *SIM, "--times", "0.5,4,32", "--out", str(out)]) == 0
    return out


def test_resume_removes_a_killed_exposure_write(captured, capsys):
    # the state a kill -9 during exposure 2's write leaves: the record says incomplete,
    # the half-written folder lies under its temporary name
    doc = json.loads((captured / "scene.json").read_text())
    rec = doc["exposures"][2]
    final = captured / rec["folder"]
    part = final.with_name(f".{final.name}.part-k1ll3d")
    os.replace(final, part)
    (part / "capture" / "partial.bin").write_bytes(b"\0" * 4096)
    tmp_json = captured / ".scene.json.k1ll.part.json"
    tmp_json.write_text("{")
    rec.update(status="incomplete", files={})
    (captured / "scene.json").write_text(json.dumps(doc))
    capsys.readouterr()
    assert main(["capture", *SIM, "--resume", "--out", str(captured)]) == 0
    assert f"removed an unfinished exposure write {part.name}" in capsys.readouterr().err
    assert not part.exists() and not tmp_json.exists()
    assert sorted(p.name for p in (captured / "exposures").iterdir()) == \
        sorted(e["folder"].split("/")[1] for e in
               json.loads((captured / "scene.json").read_text())["exposures"])


_KILL_MID_WRITE = textwrap.dedent("""
    import os, signal, sys
    import mehs.io.specim as sp
    from mehs.cli import main

    real = sp._write_contents

    def write_then_die(root, cap, cid, *, overwrite):
        real(root, cap, cid, overwrite=overwrite)
        if cid.startswith("2_"):  # exposure 2 written under its temporary name, not renamed
            os.kill(os.getpid(), signal.SIGKILL)

    sp._write_contents = write_then_die
    sys.exit(main(sys.argv[1:]))
""")


def test_resume_after_a_real_kill_during_an_exposure_write(tmp_path, capsys):
    out = tmp_path / "k"
    proc = subprocess.run([sys.executable, "-c", _KILL_MID_WRITE, "capture", *SIM, "--times",
                           "0.5,4,32", "--out", str(out)], capture_output=True, text=True,
                          timeout=300, env={**os.environ, "PYTHONPATH": os.pathsep.join(sys.path)})
    assert proc.returncode == -9, proc.stderr
    parts = list((out / "exposures").glob(".2_*.part-*"))
    assert len(parts) == 1 and any(p.is_file() for p in parts[0].rglob("*"))
    assert main(["capture", *SIM, "--resume", "--out", str(out)]) == 0
    assert "removed an unfinished exposure write" in capsys.readouterr().err
    assert not parts[0].exists()
    doc = json.loads((out / "scene.json").read_text())
    assert [e["status"] for e in doc["exposures"]] == ["complete"] * 3


def test_capture_folders_follow_the_umask(tmp_path):
    old = os.umask(0o022)
    try:
        out = tmp_path / "m"
        assert main(["capture", *SIM, "--times", "0.5,4", "--out", str(out)]) == 0
    finally:
        os.umask(old)
    for d in (out / "exposures").iterdir():
        assert d.stat().st_mode & 0o777 == 0o755, d


@pytest.mark.parametrize("sid", ["../x", "a b", ".hidden"])
def test_scene_id_that_build_would_refuse_is_refused_by_capture(tmp_path, capsys, sid):
    out = tmp_path / "s"
    assert main(["capture", *SIM, "--times", "0.5,4", "--out", str(out),
                 "--scene-id", sid]) == 2
    assert "scene id" in capsys.readouterr().err and not out.exists()


def test_resume_hint_is_a_working_command(tmp_path, capsys):
    import shlex

    out = tmp_path / "f"
    # a persistent camera disconnect stops exposure 1 of a seed-3 scene
    rc = main(["capture", *SIM, "--seed", "3", "--times", "0.5,4,32", "--out", str(out),
               "--faults", "camera:disconnect@12x50", "--timeout", "0.2"])
    err = capsys.readouterr().err
    assert rc == 2
    hint = err.split("finish with '")[1].split("'")[0]
    assert "--simulate" in hint and "--seed 3" in hint and "--size 8" in hint
    argv = shlex.split(hint)
    assert argv[:2] == ["mehs", "capture"]
    assert main(argv[1:] + ["--no-progress"]) == 0
    doc = json.loads((out / "scene.json").read_text())
    assert all(e["status"] == "complete" for e in doc["exposures"])


def test_simulate_resume_with_other_scene_options_is_refused(captured, capsys):
    doc = json.loads((captured / "scene.json").read_text())
    doc["exposures"][2].update(status="incomplete", files={})
    shutil.rmtree(captured / doc["exposures"][2]["folder"])
    (captured / "scene.json").write_text(json.dumps(doc))
    assert main(["capture", *SIM, "--resume", "--out", str(captured), "--seed", "9"]) == 2
    assert "--seed 0" in capsys.readouterr().err
    assert main(["capture", *SIM, "--resume", "--out", str(captured)]) == 0
